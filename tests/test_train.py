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
                     "--epochs", "1", "--batch", "2", "--workers", "1", "--val-limit", "4", "--max-steps", "1", "--val-xyz", "3")
    assert res.exit_code == 0 and res.stdout == b"" and res.stderr == ""  # -q: no progress bar, no summary
    assert _weights(tmp_path / "quiet" / "last.pt")["options"]["xyz_val_samples"] == 3
    meta = json.loads((tmp_path / "m.json").read_text())
    assert meta["training"]["train_objects"] == 4
    assert meta["frame"] == {"kind": "partial", "rows": 256, "radius": 0.28}
    assert meta["validation"]["val_xyz_cd_l1_x1000"] > 0


def test_a_run_logged_to_a_file_writes_progress_lines(tiny_tree, tmp_path, monkeypatch):
    """stderr not a terminal (nohup ... > run.log): a line every LINE_EVERY steps and one per validation, each its own."""
    import re

    from cli_runner import run_escape

    from escape_cli.cli import train_progress

    monkeypatch.setattr(train_progress, "LINE_EVERY", 2)
    res = run_escape("train", "--data", tiny_tree, "--out", tmp_path / "run", "--config", "tiny", "--batch", "2",
                     "--workers", "1", "--val-limit", "4", "--val-every", "3", "--max-steps", "4")
    assert res.exit_code == 0, res.stderr
    lines = [line for line in res.stderr.splitlines() if re.search(r"step \d+/4", line)]
    progress = [line for line in lines if "loss x1000" in line]
    validations = [line for line in lines if "validation:" in line]
    assert [re.search(r"step (\d+)/4", line).group(1) for line in progress] == ["2", "4"]
    assert [re.search(r"step (\d+)/4", line).group(1) for line in validations] == ["3", "4"]
    assert all(re.match(r"\d\d:\d\d:\d\d step ", line) for line in lines)
    assert re.search(r"lr \d\.\de-\d\d  \d+\.\d\d s/step$", progress[0])
    rows = list(csv.DictReader((tmp_path / "run" / "curve.csv").open()))
    assert validations[0].endswith(f"xyz CD-L1 x1000 {float(rows[0]['val_xyz_cd_l1_x1000']):.2f} (best) / input "
                                   f"{float(rows[0]['val_input_cd_l1_x1000']):.2f}")
    assert "\r" not in res.stderr and "\x1b" not in res.stderr  # no bar redraws, no terminal codes
    assert "" not in res.stderr.splitlines()  # nor the blank lines a disabled bar leaves
    assert re.search(rf"preparing {tiny_tree.name} train: \d+ samples\n.*preparing {tiny_tree.name} train: done in", res.stderr)


def test_progress_lines_name_every_validation_set_and_the_best():
    from types import SimpleNamespace

    from escape_cli.cli.train_progress import ProgressLines, format_validation

    metrics = {"val_xyz_cd_l1_x1000": 0.5897, "val_xyz_cd_l1_x1000@synth-v1": 15.46, "val_input_cd_l1_x1000@synth-v1": 30.86,
               "val_dmcd_x1000@synth-v1": 43.5, "val_xyz_cd_l1_x1000@modelnet40": 16.2, "val_input_cd_l1_x1000@modelnet40": 23.88}
    assert format_validation(metrics, best=0.6) == "score 0.5897 (best)  synth-v1 15.46 / 30.86  modelnet40 16.20 / 23.88"
    assert format_validation(metrics, best=0.58) == "score 0.5897  synth-v1 15.46 / 30.86  modelnet40 16.20 / 23.88"
    import io

    stream = io.StringIO()
    trainer = SimpleNamespace(last_metrics={}, last_step_seconds=0.5, best=0.6, lr_at=lambda step: 1e-5)
    lines = ProgressLines(trainer, stream, every=10)
    for step in range(1, 10):
        lines(step, 20, 0.25, {})
    assert stream.getvalue() == ""  # nothing before the 10th step, no validation yet
    lines(10, 20, 0.25, metrics)
    out = stream.getvalue().splitlines()
    assert out[0].endswith("step 10/20  loss x1000 250.00  lr 1.0e-05  0.50 s/step")
    assert out[1].endswith("step 10/20  validation: score 0.5897 (best)  synth-v1 15.46 / 30.86  modelnet40 16.20 / 23.88")
    lines(11, 20, 0.25, metrics)  # the same validation is not written twice
    assert len(stream.getvalue().splitlines()) == 2


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


def test_a_deeper_preset_grows_from_a_small_model_and_computes_what_it_did(tiny_tree, tmp_path):
    import torch

    from escape_cli.nn.config import get_preset
    from escape_cli.nn.model import EscapeNet
    from escape_cli.nn.train import grown_state_dict

    torch.manual_seed(3)
    small = EscapeNet(get_preset("tiny")).eval()
    deeper = replace(get_preset("tiny"), encoder_depth=3, decoder_depth=2)
    grown = EscapeNet(deeper).eval()
    grown.load_state_dict(grown_state_dict(small, deeper, 0, "m.pt"))
    rows = torch.rand(2, 256, 8)
    with torch.no_grad():
        assert torch.allclose(small(rows)[0], grown(rows)[0], atol=1e-6)
    assert get_preset("small-deep").encoder_depth == get_preset("small-deep").decoder_depth == 6
    with pytest.raises(Exception, match="another network"):  # shrinking is refused
        grown_state_dict(grown, get_preset("tiny"), 0, "m.pt")


def test_refiners_grow_from_a_small_model_start_as_nothing_and_learn(tiny_tree, tmp_path):
    import torch

    from escape_cli.nn.config import get_preset
    from escape_cli.nn.model import EscapeNet
    from escape_cli.nn.train import grown_state_dict

    torch.manual_seed(4)
    small = EscapeNet(get_preset("tiny")).eval()
    refined = replace(get_preset("tiny"), refine_stages=2)
    grown = EscapeNet(refined).eval()
    grown.load_state_dict(grown_state_dict(small, refined, 0, "m.pt"))
    rows = torch.rand(2, 256, 8)
    with torch.no_grad():
        assert torch.equal(small(rows)[0], grown(rows)[0])
    with pytest.raises(Exception, match="another network"):  # dropping refiners is refused
        grown_state_dict(grown, get_preset("tiny"), 0, "m.pt")
    assert get_preset("small-refine").refine_stages == 2

    Trainer(options(tiny_tree, tmp_path / "a", max_steps=1)).run()
    trainer = Trainer(options(tiny_tree, tmp_path / "b", max_steps=3, init=str(tmp_path / "a" / "last.pt"),
                              config="tiny-refine"))
    trainer.run()
    offsets = [stage.offset.weight.detach() for stage in trainer.model.refine]
    assert all(float(w.abs().max()) > 0 for w in offsets)  # the zero offset layers learn


def test_input_augmentation_thins_and_jitters_the_input_alone():
    from escape_cli.errors import EscapeError
    from escape_cli.nn.train import InputAugmentation

    rng = np.random.default_rng(0)
    rows = rng.random((3, 2048, 3)).astype(np.float32)
    rows[1] = rows[1, np.arange(2048) % 300]  # short scans, refilled
    rows[2] = rows[2, np.arange(2048) % 100]
    before = rows.copy()
    out = InputAugmentation(density=0.3).apply(rows, np.array([2048, 300, 100]), np.random.default_rng(1))
    assert np.array_equal(rows, before)  # a new array
    kept = [len(np.unique(o, axis=0)) for o in out]
    assert 0.3 * 2048 <= kept[0] < 2048 and 256 <= kept[1] <= 300 and kept[2] == 100
    assert np.array_equal(out[:, :256], rows[:, :256])  # the frame's rows stay
    assert np.array_equal(out[0], out[0][np.arange(2048) % kept[0]])  # refilled cyclically
    noisy = InputAugmentation(noise=0.01).apply(rows, np.array([2048, 300, 100]), np.random.default_rng(1))
    assert 0 < np.abs(noisy - rows).mean() < 0.01
    assert len(np.unique(noisy[2], axis=0)) == 100  # jittered before the refill: repeats stay repeats
    for bad in (dict(noise=-1.0), dict(noise=float("nan")), dict(density=0.0), dict(density=1.5)):
        with pytest.raises(EscapeError):
            InputAugmentation(**bad)


def test_augmentation_keeps_the_batches_and_changes_only_the_inputs(tiny_tree, tmp_path):
    from escape_cli.nn.train import sample_batch

    trainer = Trainer(options(tiny_tree, tmp_path / "a", max_steps=1, augment_noise=0.01, augment_density=0.5))
    data, idx = trainer.train_data, np.arange(2)
    plain = sample_batch(data, idx, np.random.default_rng(5), 512, 0.0, trainer.device)
    augmented = sample_batch(data, idx, np.random.default_rng(5), 512, 0.0, trainer.device,
                             trainer.opt.augmentation, np.random.default_rng(6))
    assert not np.allclose(plain[2].numpy(), augmented[2].numpy())  # inputs differ
    for a, b in ((plain[1], augmented[1]), (plain[3], augmented[3]), (plain[4], augmented[4])):
        assert np.array_equal(a.numpy(), b.numpy())  # truth, anchors: the same draws
    trainer.run()
    assert trainer.step == 1


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


def _weights(path):
    return torch.load(path, map_location="cpu", weights_only=False)


def test_bf16_trains_float32_weights_that_export_with_parity(tiny_tree, tmp_path):
    from escape_cli.nn.export import export_onnx
    from escape_cli.nn.parity import PARITY_TOLERANCE

    out = tmp_path / "run"
    trainer = Trainer(options(tiny_tree, out, precision="bf16", max_steps=3))
    metrics = trainer.run()
    assert trainer.step == 3 and metrics["val_xyz_cd_l1_x1000"] > 0
    state = _weights(out / "last.pt")
    assert state["options"]["precision"] == "bf16"
    assert json.loads((out / "options.json").read_text())["precision"] == "bf16"
    assert all(value.dtype == torch.float32 for value in state["model"].values())
    moments = [t for s in state["optimizer"]["state"].values() for t in s.values()]
    assert moments and all(t.dtype == torch.float32 for t in moments)
    meta = export_onnx(out / "best.pt", tmp_path / "m.onnx")  # raises when onnxruntime and torch differ
    assert meta["onnx_parity_max_abs"] <= PARITY_TOLERANCE


def test_training_steps_equal_those_of_the_reference_forms(tiny_tree, tmp_path):
    """The training-only forms (factored EdgeConv, max, transformer layers, threaded loss, fused AdamW) take the same steps."""
    import types

    runs = []
    for name in ("fast", "reference"):
        trainer = Trainer(options(tiny_tree, tmp_path / name, max_steps=3, xyz_weight=1.0))
        if name == "reference":  # the network's evaluation mode: its reference forms, no dropout either way
            trainer.model.train = types.MethodType(lambda self, mode=True: torch.nn.Module.train(self, False), trainer.model)
        losses = []
        trainer.run(lambda step, total, loss, metrics: losses.append(loss))
        runs.append((trainer, losses))
    (fast, fast_losses), (ref, ref_losses) = runs
    np.testing.assert_allclose(fast_losses, ref_losses, rtol=1e-5)
    dim = fast.config.dim
    for name, value in ref.model.state_dict().items():
        got, want = fast.model.state_dict()[name].numpy(), value.numpy()
        if name.endswith("in_proj_bias"):  # the key bias: no effect on the output, a zero gradient up to
            got, want = np.delete(got, slice(dim, 2 * dim)), np.delete(want, slice(dim, 2 * dim))  # rounding, which Adam scales up
        np.testing.assert_allclose(got, want, atol=1e-6, err_msg=name)
    assert fast.optimizer.param_groups[0]["fused"]


def test_the_fused_adamw_update_is_that_of_the_per_tensor_loop():
    """The fused AdamW that training uses takes the steps of the plain per-tensor loop, to rounding."""
    torch.manual_seed(0)
    weights = [torch.randn(7, 5), torch.randn(5)]
    updated = []
    for fused in (True, False):
        params = [torch.nn.Parameter(w.clone()) for w in weights]
        optimizer = torch.optim.AdamW(params, lr=1e-2, weight_decay=0.05, fused=fused, foreach=False if not fused else None)
        for step in range(5):
            optimizer.zero_grad()
            loss = sum(((p - 0.1 * step) ** 3).sum() for p in params)
            loss.backward()
            optimizer.step()
        assert optimizer.param_groups[0]["fused"] is fused
        updated.append([p.detach().numpy().copy() for p in params])
    for got, want in zip(*updated):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_resume_keeps_the_runs_precision_and_reads_checkpoints_without_it(tiny_tree, tmp_path):
    from cli_runner import run_escape

    out = tmp_path / "run"
    common = ("-q", "train", "--data", tiny_tree, "--out", out, "--config", "tiny", "--batch", "2",
              "--workers", "1", "--val-limit", "4")
    assert run_escape(*common, "--precision", "bf16", "--max-steps", "1").exit_code == 0
    res = run_escape(*common, "--resume", "--max-steps", "2")
    assert res.exit_code == 0, res.stderr
    state = _weights(out / "last.pt")
    assert state["step"] == 2 and state["options"]["precision"] == "bf16"
    del state["options"]["precision"]  # a checkpoint from before --precision
    torch.save(state, out / "last.pt")
    res = run_escape(*common, "--resume", "--max-steps", "3")
    assert res.exit_code == 0, res.stderr
    state = _weights(out / "last.pt")
    assert state["step"] == 3 and state["options"]["precision"] == "fp32"
    res = run_escape(*common, "--resume", "--precision", "fp16")
    assert res.exit_code == 2 and "--precision" in res.stderr


def test_resume_keeps_every_option_of_the_run_not_given_again(tiny_tree, tmp_path):
    """A bare `--resume` goes on as the run was (network, data views, learning rate, seed...), not from the defaults."""
    from cli_runner import run_escape

    out = tmp_path / "run"
    res = run_escape("-q", "train", "--data", tiny_tree, "--out", out, "--config", "tiny", "--batch", "2", "--lr", "1e-3",
                     "--views", "1", "--seed", "5", "--recall-weight", "2", "--val-limit", "4", "--val-xyz", "3",
                     "--snapshot-every", "1", "--workers", "1", "--max-steps", "1", "--cache", tmp_path / "cache",
                     "--val-data", tiny_tree)
    assert res.exit_code == 0, res.stderr
    res = run_escape("-q", "train", "--data", tiny_tree, "--out", out, "--resume", "--max-steps", "2", "--workers", "1")
    assert res.exit_code == 0, res.stderr
    state = _weights(out / "last.pt")
    options = state["options"]
    assert options["max_steps"] == 2 and state["step"] == 2
    kept = {key: options[key] for key in ("config", "batch", "lr", "views_per_object", "seed", "recall_weight", "val_limit",
                                          "xyz_val_samples", "snapshot_every")}
    assert kept == {"config": "tiny", "batch": 2, "lr": 1e-3, "views_per_object": 1, "seed": 5, "recall_weight": 2.0,
                    "val_limit": 4, "xyz_val_samples": 3, "snapshot_every": 1}
    assert options["cache"] == str(tmp_path / "cache") and list(options["val_data"]) == [str(tiny_tree)]
    assert not (out / "cache").exists(), "the resumed run kept its cache folder"
    assert json.loads((out / "options.json").read_text())["lr"] == 1e-3
    # an option given again replaces the run's, even when it is the default value
    res = run_escape("-q", "train", "--data", tiny_tree, "--out", out, "--resume", "--lr", "5e-4", "--max-steps", "3", "--workers", "1")
    assert res.exit_code == 0, res.stderr
    options = _weights(out / "last.pt")["options"]
    assert options["lr"] == 5e-4 and options["views_per_object"] == 1
    # the network cannot change under a run
    res = run_escape("-q", "train", "--data", tiny_tree, "--out", out, "--resume", "--config", "small", "--max-steps", "4")
    assert res.exit_code == 2 and "--config" in res.stderr and "tiny" in res.stderr
    assert _weights(out / "last.pt")["step"] == 3


def test_resume_without_data_keeps_the_runs_datasets(tiny_tree, tmp_path):
    """`--resume` needs only --out: the run's datasets (every --data, in order) go on; a new run needs --data."""
    from cli_runner import run_escape

    second = tmp_path / "second"
    write_tiny_pcn_tree(second)
    out = tmp_path / "run"
    res = run_escape("-q", "train", "--data", tiny_tree, "--data", second, "--out", out, "--config", "tiny",
                     "--batch", "2", "--workers", "1", "--val-limit", "4", "--max-steps", "1")
    assert res.exit_code == 0, res.stderr
    res = run_escape("-q", "train", "--out", out, "--resume", "--max-steps", "2", "--workers", "1")
    assert res.exit_code == 0, res.stderr
    state = _weights(out / "last.pt")
    options = state["options"]
    assert state["step"] == 2
    assert options["data"] == str(tiny_tree) and list(options["extra_data"]) == [str(second)]
    res = run_escape("-q", "train", "--out", tmp_path / "none", "--resume", "--workers", "1")
    assert res.exit_code != 0 and "cannot resume" in res.stderr and "Traceback" not in res.stderr
    res = run_escape("-q", "train", "--out", tmp_path / "fresh", "--config", "tiny")
    assert res.exit_code == 2 and "--data" in res.stderr and "missing" in res.stderr


def test_resume_keeps_the_record_of_init_and_refuses_a_new_one(tiny_tree, tmp_path):
    from cli_runner import run_escape

    common = ("-q", "train", "--data", tiny_tree, "--config", "tiny", "--batch", "2", "--workers", "1", "--val-limit", "4")
    first, second = tmp_path / "first", tmp_path / "second"
    assert run_escape(*common, "--out", first, "--max-steps", "1").exit_code == 0
    start = first / "last.pt"
    assert run_escape(*common, "--out", second, "--init", start, "--max-steps", "1").exit_code == 0
    res = run_escape(*common, "--out", second, "--resume", "--max-steps", "2")
    assert res.exit_code == 0, res.stderr
    assert _weights(second / "last.pt")["options"]["init"] == str(start)
    assert json.loads((second / "options.json").read_text())["init"] == str(start)
    res = run_escape(*common, "--out", second, "--resume", "--init", start, "--max-steps", "3")
    assert res.exit_code == 2 and "--init" in res.stderr
    assert _weights(second / "last.pt")["step"] == 2


def test_runs_share_a_cache_folder(tiny_tree, tmp_path, monkeypatch):
    import escape_cli.nn.samples as samples

    cache = tmp_path / "shared"
    first = Trainer(options(tiny_tree, tmp_path / "a", cache=str(cache)))
    assert len(list(cache.glob("prepared-*.npz"))) == 2  # train and val
    assert not (tmp_path / "a" / "cache").exists()

    def no_preparing(*args, **kw):
        raise AssertionError("prepared again")

    monkeypatch.setattr(samples, "_run_parallel", no_preparing)
    second = Trainer(options(tiny_tree, tmp_path / "b", cache=str(cache)))
    np.testing.assert_array_equal(second.train_data.inputs, first.train_data.inputs)
    np.testing.assert_array_equal(second.val_data.anchors, first.val_data.anchors)
    assert json.loads((second.out / "options.json").read_text())["cache"] == str(cache)


def test_two_runs_preparing_one_cache_at_once_prepare_it_once(tiny_tree, tmp_path, monkeypatch):
    import threading
    import time

    import escape_cli.nn.samples as samples

    prepared = []
    real = samples._run_parallel

    def slow(func, jobs, workers, label):
        prepared.append(label)
        time.sleep(0.3)  # long enough for the other run to arrive meanwhile
        return real(func, jobs, workers, label)

    monkeypatch.setattr(samples, "_run_parallel", slow)
    cache = tmp_path / "shared"
    trainers, errors = {}, []

    def start(name):
        try:
            trainers[name] = Trainer(options(tiny_tree, tmp_path / name, cache=str(cache)))
        except Exception as err:  # pragma: no cover - reported below
            errors.append(err)

    threads = [threading.Thread(target=start, args=(name,)) for name in ("a", "b")]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    assert sorted(prepared) == [f"preparing {tiny_tree.name} train", f"preparing {tiny_tree.name} val"]  # each split once, by one of the runs
    np.testing.assert_array_equal(trainers["a"].train_data.inputs, trainers["b"].train_data.inputs)
    assert sorted(p.name for p in cache.iterdir() if not p.name.startswith("prepared-")) == [".lock"]  # no temporaries


def test_several_validation_sets_are_logged_by_name_and_scored_together(tiny_tree, tmp_path):
    from escape_cli.errors import EscapeError
    from escape_cli.nn.average import average_checkpoints
    from escape_cli.nn.export import export_onnx

    other = tmp_path / "second"
    write_tiny_pcn_tree(other, seed=5, objects=1)
    out = tmp_path / "run"
    sets = (str(tiny_tree), str(other))
    trainer = Trainer(options(tiny_tree, out, val_data=sets, max_steps=2, snapshot_every=1, val_every=1))
    metrics = trainer.run()
    names = [tiny_tree.name, "second"]
    assert list(trainer.val_sets) == names and len(trainer.val_sets["second"]) == 2
    rows = list(csv.DictReader((out / "curve.csv").open()))
    assert len(rows) == 2
    kinds = ("val_dmcd_x1000", "val_xyz_cd_l1_x1000", "val_input_cd_l1_x1000")
    assert {f"{kind}@{name}" for kind in kinds for name in names} | {"val_xyz_cd_l1_x1000"} <= set(rows[-1])
    ratios = [float(rows[-1][f"val_xyz_cd_l1_x1000@{n}"]) / float(rows[-1][f"val_input_cd_l1_x1000@{n}"]) for n in names]
    assert float(rows[-1]["val_xyz_cd_l1_x1000"]) == pytest.approx(np.mean(ratios))  # the selection score
    assert trainer.best == pytest.approx(min(float(r["val_xyz_cd_l1_x1000"]) for r in rows))
    assert metrics["val_xyz_cd_l1_x1000"] == pytest.approx(float(rows[-1]["val_xyz_cd_l1_x1000"]), rel=1e-6)

    meta = export_onnx(out / "best.pt", tmp_path / "m.onnx")
    assert f"val_xyz_cd_l1_x1000@{names[1]}" in meta["validation"]
    averaged = average_checkpoints(sorted((out / "snapshots").glob("step*.pt")), tmp_path / "avg.pt")
    assert set(averaged["metrics"]) == {"step"} | {k for k in rows[-1] if k.startswith("val_")}
    export_onnx(tmp_path / "avg.pt", tmp_path / "avg.onnx")

    with pytest.raises(EscapeError, match="validates on"):  # the curve's columns cannot change on resume
        Trainer(options(tiny_tree, out, max_steps=3), resume=True)


def test_default_validation_keeps_its_columns_and_sets_need_distinct_names(tiny_tree, tmp_path):
    from escape_cli.errors import EscapeError
    from escape_cli.nn.train import set_names

    Trainer(options(tiny_tree, tmp_path / "run", max_steps=1)).run()
    header = (tmp_path / "run" / "curve.csv").read_text().splitlines()[0].split(",")
    assert header == ["step", "epoch", "train_loss_x1000", "val_dmcd_x1000", "val_xyz_cd_l1_x1000",
                      "val_input_cd_l1_x1000", "lr", "train_seconds"]
    assert set_names(["/a/modelnet40", "/b/synth"]) == ["modelnet40", "synth"]
    with pytest.raises(EscapeError, match="two validation sets are named 'synth'"):
        set_names(["/a/synth", "/b/synth"])
