"""Packaged models by name: `--model NAME` (or a path) in every command that runs the network, and `--help` lists the names."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from cli_runner import run_escape
from conftest import REPO
from escape_cli import packaged_models
from escape_cli.errors import ModelError
from tests_support import partial_cloud

ESCAPE = REPO / ".venv" / "bin" / "escape"


@pytest.fixture(scope="module")
def second_tiny_model(tmp_path_factory):
    """Another untrained tiny network (other weights than `tiny_model`'s)."""
    pytest.importorskip("torch")
    from escape_cli.nn.export import export_onnx
    from tests_support import write_tiny_checkpoint

    folder = tmp_path_factory.mktemp("second_tiny_model")
    write_tiny_checkpoint(folder / "tiny.pt", seed=1)
    export_onnx(folder / "tiny.pt", folder / "tiny.onnx")
    return folder / "tiny.onnx"


def _package(folder, model, name):
    shutil.copy(model, folder / f"escape-{name}.onnx")
    shutil.copy(model.with_suffix(".json"), folder / f"escape-{name}.json")
    return folder / f"escape-{name}.onnx"


@pytest.fixture
def packaged(tmp_path, monkeypatch, tiny_model, second_tiny_model):
    """A models folder holding two packaged models, `small` and `synth`, in place of the package's."""
    folder = tmp_path / "models"
    folder.mkdir()
    paths = {"small": _package(folder, tiny_model, "small"), "synth": _package(folder, second_tiny_model, "synth")}
    (folder / "README.md").write_text("not a model\n")
    (folder / "escape-half.json").write_text("{}")  # metadata alone is no model
    (folder / "other.onnx").write_bytes(b"")  # not escape-<name>.onnx
    monkeypatch.setenv(packaged_models.FOLDER_ENV, str(folder))
    monkeypatch.delenv(packaged_models.MODEL_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    return paths


@pytest.fixture
def scan(tmp_path, rng):
    from escape_cli.io import write_points

    path = tmp_path / "scan.ply"
    write_points(path, partial_cloud(rng, 400))
    return path


def test_names_are_the_onnx_files_of_the_folder_default_first(tmp_path, monkeypatch):
    monkeypatch.setenv(packaged_models.FOLDER_ENV, str(tmp_path))
    for name in ("escape-zeta.onnx", "escape-alpha.onnx", "escape-small.onnx", "escape-x.json", "escape-.onnx",
                 "escape-a b.onnx", "small.onnx", "README.md"):
        (tmp_path / name).write_bytes(b"")
    assert packaged_models.names() == ["small", "alpha", "zeta"]
    assert packaged_models.listing() == "small, alpha, zeta"
    monkeypatch.setenv(packaged_models.FOLDER_ENV, str(tmp_path / "absent"))
    assert packaged_models.names() == [] and packaged_models.listing() == "none"


def test_the_package_folder_is_where_importlib_resources_finds_it(monkeypatch):
    from importlib import resources

    monkeypatch.delenv(packaged_models.FOLDER_ENV, raising=False)
    assert packaged_models.folder() == resources.files("escape_cli") / "models"
    assert "small" in packaged_models.names()


def test_resolve_paths_names_and_the_default(packaged, monkeypatch, tmp_path):
    resolve = packaged_models.resolve
    assert resolve(None) == packaged["small"] == resolve("small")
    assert resolve("synth") == packaged["synth"]
    monkeypatch.setenv(packaged_models.MODEL_ENV, "synth")
    assert resolve(None) == packaged["synth"]
    monkeypatch.setenv(packaged_models.MODEL_ENV, str(packaged["small"]))
    assert resolve(None) == packaged["small"]
    monkeypatch.setenv(packaged_models.MODEL_ENV, "nope")
    with pytest.raises(ModelError, match=r"^\$ESCAPE_MODEL is 'nope': no packaged model is named 'nope' \(packaged models: small, synth\)"):
        resolve(None)
    # paths stay paths, existing or not (read_metadata reports a missing one)
    assert resolve("runs/best.onnx") == tmp_path.joinpath("runs/best.onnx").relative_to(tmp_path)
    assert resolve(str(packaged["synth"])) == packaged["synth"]
    assert resolve(packaged["synth"]) == packaged["synth"]
    # an existing file is a path, even when it is called like a packaged model
    (tmp_path / "synth").write_bytes(b"x")
    assert str(resolve("synth")) == "synth"
    with pytest.raises(ModelError, match="no packaged model is named 'other'.*small, synth"):
        resolve("other")
    (tmp_path / "models-here").mkdir()
    with pytest.raises(ModelError, match="^models-here is a folder, and no packaged model is named 'models-here'"):
        resolve("models-here")


def _complete(scan, out, *model):
    res = run_escape("-q", "complete", scan, "-o", out, "--points", "512", *model)
    assert res.exit_code == 0, res.stderr
    return out.read_bytes()


def test_complete_picks_the_named_model(packaged, scan, tmp_path):
    by_path = {name: _complete(scan, tmp_path / f"{name}-path.ply", "--model", path) for name, path in packaged.items()}
    assert by_path["small"] != by_path["synth"]  # two networks, two completions
    assert _complete(scan, tmp_path / "synth.ply", "--model", "synth") == by_path["synth"]
    assert _complete(scan, tmp_path / "m.ply", "-m", "small") == by_path["small"]
    assert _complete(scan, tmp_path / "default.ply") == by_path["small"]


def test_a_batch_hands_the_name_to_its_workers(packaged, scan, tmp_path):
    expected = _complete(scan, tmp_path / "one.ply", "--model", packaged["synth"])
    shutil.copy(scan, tmp_path / "scan2.ply")
    res = run_escape("-q", "complete", scan, tmp_path / "scan2.ply", "-o", tmp_path / "out", "--points", "512",
                     "--model", "synth", "--workers", "1")
    assert res.exit_code == 0, res.stderr
    assert (tmp_path / "out" / "scan.ply").read_bytes() == (tmp_path / "out" / "scan2.ply").read_bytes() == expected


@pytest.mark.parametrize("command", ["complete", "eval"])
def test_an_unknown_name_is_one_line_listing_the_names(packaged, scan, tmp_path, command):
    if command == "complete":
        argv = ["complete", scan, "-o", tmp_path / "out.ply", "--model", "nope"]
    else:
        argv = ["eval", "--dataset", "pairs", "--root", tmp_path, "--model", "nope"]
    res = run_escape(*argv)
    assert res.exit_code == 1
    assert res.stderr_lines == [
        "escape: error: no packaged model is named 'nope' (packaged models: small, synth); "
        "give one of those names or a model file's path"
    ]
    assert not (tmp_path / "out.ply").exists()
    res = run_escape(*argv[:-1], "missing.onnx")  # a path that is not there: as before
    assert res.exit_code == 1 and res.stderr_lines == ["escape: error: model file missing.onnx does not exist"]


def test_eval_takes_a_name(packaged, tmp_path, rng):
    from escape_cli.io import write_points

    pairs = tmp_path / "pairs"
    pairs.mkdir()
    write_points(pairs / "a_partial.ply", partial_cloud(rng, 300))
    write_points(pairs / "a_complete.ply", partial_cloud(rng, 600))
    reports = {}
    for model in ("synth", str(packaged["synth"]), "small"):
        res = run_escape("-q", "eval", "--dataset", "pairs", "--root", pairs, "--model", model, "--json", "--no-baseline")
        assert res.exit_code == 0, res.stderr
        report = json.loads(res.stdout)
        reports[model] = (report["settings"]["model"], json.dumps(report["samples"]))
    assert reports["synth"][0] == str(packaged["synth"]) and reports["small"][0] == str(packaged["small"])
    assert reports["synth"] == reports[str(packaged["synth"])] and reports["synth"][1] != reports["small"][1]


def _escape(*args, env_extra, cwd):
    env = {**os.environ, "COLUMNS": "250", **env_extra}
    env.pop(packaged_models.MODEL_ENV, None)
    return subprocess.run([str(ESCAPE), *map(str, args)], capture_output=True, text=True, timeout=300, env=env, cwd=cwd)


@pytest.mark.skipif(not ESCAPE.exists(), reason="needs the installed escape command")
def test_help_lists_the_names_and_the_entry_point_preloads_by_name(packaged, scan, tmp_path):
    env = {packaged_models.FOLDER_ENV: os.environ[packaged_models.FOLDER_ENV]}
    for command in ("complete", "eval"):
        res = _escape(command, "--help", env_extra=env, cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        assert "A packaged model (small, synth) or an exported .onnx file" in res.stdout, res.stdout
    # one scan: cli/launch.py starts the named model's load before the CLI is imported
    expected = _complete(scan, tmp_path / "path.ply", "--model", packaged["synth"])
    res = _escape("-q", "complete", scan, "-o", tmp_path / "named.ply", "--points", "512", "--model", "synth",
                  env_extra=env, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "named.ply").read_bytes() == expected


def test_the_help_of_the_package_lists_its_own_models():
    res = subprocess.run([sys.executable, "-m", "escape_cli", "complete", "--help"], capture_output=True, text=True,
                         timeout=300, env={**os.environ, "COLUMNS": "250"}, cwd=REPO)
    assert res.returncode == 0, res.stderr
    shipped = sorted(p.name[len("escape-"):-len(".onnx")] for p in (REPO / "src" / "escape_cli" / "models").glob("escape-*.onnx"))
    listed = res.stdout.split("A packaged model (", 1)[1].split(")", 1)[0].split(", ")
    assert sorted(listed) == shipped and listed[0] == "small"
