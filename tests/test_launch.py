"""The entry point starts the model's load only for a single `escape complete`, and never changes an outcome."""

from __future__ import annotations

import pytest

from escape_cli.cli.argv import preload_target


@pytest.mark.parametrize("args, wanted", [
    (["complete", "a.ply", "-o", "b.ply"], (True, None)),
    (["-q", "-v", "complete", "a.ply", "-o", "b.ply"], (True, None)),
    (["complete", "a.ply", "-o", "b.ply", "--model", "m.onnx"], (True, "m.onnx")),
    (["complete", "a.ply", "-m", "m.onnx", "-o", "b.ply"], (True, "m.onnx")),
    (["complete", "--model=m.onnx", "a.ply", "-o", "b.ply"], (True, "m.onnx")),
    (["complete", "a.ply", "-o", "out", "--workers", "2"], (False, None)),
    (["complete", "--files-from", "list.txt", "-o", "out"], (False, None)),
    (["complete", "--help"], (False, None)),
    (["anchors", "a.ply", "-o", "b.ply"], (False, None)),
    (["--version"], (False, None)),
    ([], (False, None)),
])
def test_preload_target(args, wanted):
    assert preload_target(args) == wanted
