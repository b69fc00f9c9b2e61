"""A job whose extra is not installed says which extra to install, in one line (escape_cli.extras)."""

from __future__ import annotations

import sys

import pytest

from cli_runner import run_escape


def test_synth_without_open3d_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # as if it were not installed
    res = run_escape("dataset", "synth", "--out", tmp_path / "d", "--train", "1")
    assert res.exit_code == 1
    assert res.stderr_lines == [
        "escape: error: escape dataset synth needs open3d, which is not installed: pip install 'escape-cli[synth]'"
    ]
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("command", [["train", "--data", "d", "--out", "r"], ["export-onnx", "x.pt", "-o", "m.onnx"],
                                     ["average-checkpoints", "a.pt", "-o", "b.pt"]])
def test_training_commands_without_torch_name_the_extra(monkeypatch, command):
    monkeypatch.setitem(sys.modules, "torch", None)
    res = run_escape(*command)
    assert res.exit_code == 1 and len(res.stderr_lines) == 1
    assert "needs torch, which is not installed: pip install 'escape-cli[train]'" in res.stderr
    assert "--index-url https://download.pytorch.org/whl/cpu" in res.stderr


def test_a_broken_install_is_reported_as_such(monkeypatch):
    """Installed but not loadable (a missing system library): the message says so, in one line."""
    import importlib

    from escape_cli.errors import MissingDependencyError
    from escape_cli.extras import require

    def broken(name, *args, **kwargs):
        raise OSError("libGL.so.1: cannot open shared object file: No such file or directory")

    monkeypatch.setattr(importlib, "import_module", broken)
    with pytest.raises(MissingDependencyError, match=r"installed but cannot be loaded: libGL\.so\.1.*libgl1"):
        require("open3d", "escape dataset synth")
