"""Every command-line usage error is one line `escape: error: OPTION: what is wrong (see --help)`, exit 2.

typer (click, pydantic) would print a multi-line box, or accept nan, inf and absurd
values; `main()` turns each into one line in the wording of `escape_cli.core.params`,
with the option's name. Data errors are one line too, with exit code 1; `--help` still
shows the full usage of every command.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_runner import run_escape

NEEDS_TORCH = ("train",)  # the train command imports torch to check --device and --config

# (argv, what the one line must say); every path here may not exist: parsing comes first
USAGE_ERRORS = [
    (["complete", "s.ply", "-o", "o.ply", "--points", "0"], "--points: must be at least 1, got 0"),
    (["complete", "s.ply", "-o", "o.ply", "--points", "abc"], "--points: must be an integer, got 'abc'"),
    (["complete", "s.ply", "-o", "o.ply", "--points", "1.5"], "--points: must be an integer, got 1.5"),
    (["complete", "s.ply", "-o", "o.ply", "--points"], "Option '--points' requires an argument"),
    (["complete", "s.ply", "-o", "o.ply", "--snap-radius", "-1"], "--snap-radius: must be at least 0, got -1"),
    (["complete", "s.ply", "-o", "o.ply", "--anchor-sets", "0"], "--anchor-sets: must be at least 1, got 0"),
    (["complete", "s.ply", "-o", "o.ply", "--anchor-sets", "9"], "--anchor-sets: must be at most 8, the model's anchors"),
    (["complete", "s.ply", "-o", "o.ply", "--snap-radius", "inf"], "--snap-radius: must be a finite number, got inf"),
    (["complete", "s.ply", "-o", "o.ply", "--snap-radius", "nan"], "--snap-radius: must be a finite number, got nan"),
    (["complete", "s.ply", "-o", "o.ply", "--workers", "0"], "--workers: must be at least 1, got 0"),
    (["complete", "s.ply", "-o", "o.ply", "--normalize", "bogus"], "--normalize: must be auto or none"),
    (["complete", "s.ply", "-o", "o.ply", "--solver", "bogus"], "--solver: must be batched or scipy"),
    (["complete", "s.ply"], "--output: missing (required)"),
    (["complete", "s.ply", "-o", "o.ply", "-q"], "-q is a global option: put it before the command"),
    (["complete", "s.ply", "-o", "o.ply", "-vv"], "-v is a global option"),
    (["complete", "s.ply", "-o", "o.ply", "--bogus"], "No such option: --bogus"),
    (["complete", "s.ply", "-o", "o.ply", "--keep-input=3"], "Option '--keep-input' does not take a value"),
    (["bogus"], "No such command 'bogus'"),
    (["anchors", "s.ply", "--json", "--k", "3"], "--k: must be at least 4, got 3"),
    (["anchors", "s.ply", "--json", "--knn", "2"], "--knn: must be at least 3, got 2"),
    (["anchors", "s.ply", "--json", "--radius", "nan"], "--radius: must be a finite number, got nan"),
    (["anchors", "s.ply", "--json", "--radius", "inf"], "--radius: must be a finite number, got inf"),
    (["anchors", "s.ply", "--json", "--radius", "1e400"], "--radius: must be a finite number, got inf"),
    (["anchors", "s.ply", "--json", "--radius", "0"], "--radius: must be greater than 0, got 0"),
    (["anchors", "s.ply", "--json", "--method", "bogus"], "--method: 'bogus' is not one of 'ball', 'fps', 'cluster'"),
    (["encode", "s.ply", "-o", "d.npy", "--k", "abc"], "--k: must be an integer, got 'abc'"),
    (["encode", "s.ply", "-o", "d.npy", "--radius", "-inf"], "--radius: must be a finite number, got -inf"),
    (["decode", "d.npy", "-a", "a.ply", "-o", "o.ply", "--solver", "bogus"], "--solver: 'bogus' is not one of"),
    (["decode", "d.npy", "-o", "o.ply"], "--anchors: missing (required)"),
    (["render", "s.ply", "-o", "r.png", "--views", "5"], "--views: must be at most 4, got 5"),
    (["render", "s.ply", "-o", "r.png", "--views", "0"], "--views: must be at least 1, got 0"),
    (["render", "s.ply", "-o", "r.png", "--size", "8"], "--size: must be at least 16, got 8"),
    (["eval", "--root", "r", "--drop", "2"], "--drop: must be at most 0.95, got 2"),
    (["eval", "--root", "r", "--drop", "nan"], "--drop: must be a finite number, got nan"),
    (["eval", "--root", "r", "--noise", "-1"], "--noise: must be at least 0, got -1"),
    (["eval", "--root", "r", "--noise", "inf"], "--noise: must be a finite number, got inf"),
    (["eval", "--root", "r", "--limit", "0"], "--limit: must be at least 1, got 0"),
    (["eval", "--root", "r", "--seed", "-1"], "--seed: must be at least 0, got -1"),
    (["eval", "--root", "r", "--dataset", "bogus"], "--dataset: must be pcn, pair, pairs or kitti"),
    (["eval", "--root", "r", "--snap-radius", "inf"], "--snap-radius: must be a finite number, got inf"),
    (["eval", "--root", "r", "--anchor-sets", "0"], "--anchor-sets: must be at least 1, got 0"),
    (["dataset", "synth", "-o", "ds", "--train", "-1"], "--train: must be at least 0, got -1"),
    (["dataset", "synth", "-o", "ds", "--train", "99999999999999999999"], "--train: must be at most 100000"),
    (["dataset", "synth", "-o", "ds", "--train", "1", "--views", "0"], "--views: must be at least 1, got 0"),
    (["dataset", "synth", "-o", "ds", "--train", "1", "--complete-points", "8"], "--complete-points: must be at least 16, got 8"),
    (["dataset", "synth", "-o", "ds", "--train", "1", "--seed", "-1"], "--seed: must be at least 0, got -1"),
    (["dataset", "synth", "-o", "ds", "--train", "1", "--workers", "0"], "--workers: must be at least 1, got 0"),
    (["export-onnx", "c.pt", "-o", "m.onnx", "--opset", "abc"], "--opset: must be an integer, got 'abc'"),
    (["train", "--data", "d", "--out", "r", "--lr", "nan"], "--lr: must be a finite number, got nan"),
    (["train", "--data", "d", "--out", "r", "--lr", "0"], "--lr: must be greater than 0, got 0"),
    (["train", "--data", "d", "--out", "r", "--lr", "-1"], "--lr: must be greater than 0, got -1"),
    (["train", "--data", "d", "--out", "r", "--seed", "-1"], "--seed: must be at least 0, got -1"),
    (["train", "--data", "d", "--out", "r", "--seed", "99999999999999999999"], "--seed: must be at most"),
    (["train", "--data", "d", "--out", "r", "--threads", "-1"], "--threads: must be at least 0, got -1"),
    (["train", "--data", "d", "--out", "r", "--workers", "0"], "--workers: must be at least 1, got 0"),
    (["train", "--data", "d", "--out", "r", "--denoise", "-0.5"], "--denoise: must be at least 0, got -0.5"),
    (["train", "--data", "d", "--out", "r", "--augment-noise", "-0.1"], "--augment-noise: must be at least 0, got -0.1"),
    (["train", "--data", "d", "--out", "r", "--augment-density", "0"], "--augment-density: must be greater than 0, got 0"),
    (["train", "--data", "d", "--out", "r", "--augment-density", "1.5"], "--augment-density: must be at most 1, got 1.5"),
    (["train", "--data", "d", "--out", "r", "--xyz-weight", "inf"], "--xyz-weight: must be a finite number, got inf"),
    (["train", "--data", "d", "--out", "r", "--max-steps", "0"], "--max-steps: must be at least 1, got 0"),
    (["train", "--data", "d", "--out", "r", "--val-every", "-1"], "--val-every: must be at least 0, got -1"),
    (["train", "--data", "d", "--out", "r", "--val-limit", "0"], "--val-limit: must be at least 1, got 0"),
    (["anchors", "s.ply", "-o", "o.ply", "--format", "bogus"], "unknown format 'bogus'; use one of ply, pcd"),
    (["anchors", "s.ply", "--json", "--input-format", "bogus"], "unknown format 'bogus'; use one of ply, pcd"),
    (["anchors", "s.ply", "-o", "o.bogus"], "unknown format '.bogus' for o.bogus; use --format"),
    (["anchors", "s.ply", "-o", "anchors"], "cannot tell the format of anchors (no extension); use --format"),
    (["complete", "s.ply", "-o", "o.ply", "--shard", "3/2"], "--shard: must be I/N with 0 <= I < N"),
    (["eval", "--root", "d", "--split", "bogus"], "--split: must be train, val or test"),
    (["eval", "--root", "d", "--reference", "refs"], "--reference: only for --dataset kitti"),
    (["eval", "--dataset", "kitti", "--root", "d", "--reference-up", "z"], "--reference-up: needs --reference"),
    (["eval", "--dataset", "kitti", "--root", "d", "--reference", "r", "--reference-up", "w"], "--reference-up: must be x, y or z"),
    (["render", "s.ply", "-o", "r.jpg"], "unknown image format '.jpg' for r.jpg; render writes .png"),
    (["train", "--data", "d", "--out", "r", "--config", "bogus"], "--config: unknown config 'bogus'"),
    (["train", "--data", "d", "--out", "r", "--device", "bogus"], "--device: unknown device 'bogus'"),
]


def _id(case) -> str:
    argv, _ = case
    return " ".join(argv)[:60]


@pytest.mark.parametrize(("argv", "expected"), USAGE_ERRORS, ids=[_id(c) for c in USAGE_ERRORS])
def test_usage_error_is_one_line_with_exit_code_2(tmp_path, monkeypatch, argv, expected):
    if argv[0] in NEEDS_TORCH:
        pytest.importorskip("torch")
    monkeypatch.chdir(tmp_path)  # relative names: nothing may be created or read
    result = run_escape(*argv)
    assert result.exit_code == 2, result.stderr
    assert len(result.stderr_lines) == 1 and result.stderr.startswith("escape: error: "), result.stderr
    line = result.stderr_lines[0]
    assert expected in line, line
    assert line.endswith(" (see --help)"), line
    assert result.stdout == b""
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["anchors", "missing.ply", "--json"], "missing.ply: no such file"),
        (["complete", "missing.ply", "-o", "o.ply", "--model", "missing.onnx"], "model file missing.onnx does not exist"),
        (["dataset", "info", "missing"], "missing"),
        (["eval", "--dataset", "pair", "--root", "missing"], "missing is not a folder"),
        (["eval", "--dataset", "pairs", "--root", "missing"], "missing is not a folder"),
        (["eval", "--dataset", "kitti", "--root", "missing", "--reference", "refs/"], "--reference refs: no such folder"),
    ],
)
def test_data_error_is_one_line_with_exit_code_1(tmp_path, monkeypatch, argv, expected):
    monkeypatch.chdir(tmp_path)
    result = run_escape(*argv)
    assert result.exit_code == 1, result.stderr
    assert len(result.stderr_lines) == 1 and result.stderr_lines[0].startswith("escape: error: "), result.stderr
    assert expected in result.stderr


COMMANDS = [
    [], ["anchors"], ["encode"], ["decode"], ["complete"], ["eval"], ["render"], ["train"], ["export-onnx"],
    ["average-checkpoints"], ["dataset"], ["dataset", "synth"], ["dataset", "info"],
]  # fmt: skip


@pytest.mark.parametrize("command", COMMANDS, ids=[" ".join(c) or "escape" for c in COMMANDS])
def test_help_still_shows_the_full_usage(command):
    result = run_escape(*command, "--help")
    assert result.exit_code == 0 and result.stderr == ""
    text = result.stdout.decode()
    assert f"Usage: escape {' '.join(command)}".rstrip() in " ".join(text.split())
    assert "--help" in text and len(text.splitlines()) > 5


def test_complete_help_names_the_ray_extra(monkeypatch):
    """rich markup would take `[ray]` for a style and print "needs escape-cli"."""
    monkeypatch.setenv("COLUMNS", "400")  # each option's help on one line of the box
    text = " ".join(run_escape("complete", "--help").stdout.decode().split())
    assert "needs escape-cli[ray])" in text


README = Path(__file__).resolve().parents[1] / "README.md"


def _readme_row(start: str) -> str:
    return next(line for line in README.read_text().splitlines() if line.startswith(start))


def test_readme_points_row_gives_the_shipped_models_ceiling():
    from escape_cli.inference import default_model_path, max_output_points, read_metadata

    ceiling = max_output_points(read_metadata(default_model_path()))
    row = _readme_row("| `--points M`")
    assert f"{ceiling} for the shipped model" in row, row


def test_readme_commands_table_lists_every_eval_dataset():
    line = run_escape("eval", "--root", "r", "--dataset", "bogus").stderr
    datasets = line.split("must be ")[1].split(" (see")[0].replace(" or ", ", ").split(", ")
    assert "\\|".join(datasets) in _readme_row("| `escape eval --dataset "), datasets

