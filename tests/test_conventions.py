"""What users of a Python CLI expect: python -m, shell completion, one --json, every format in --help,
the API taking other libraries' clouds, progress on stderr."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cli_runner import run_escape
from conftest import REPO
from escape_cli.formats import FORMATS
from tests_support import partial_cloud


def run_module(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "escape_cli", *args], capture_output=True, text=True, timeout=120,
                          cwd=REPO, env={**os.environ, **(env or {})})


def test_python_dash_m_is_the_escape_command():
    from escape_cli import __version__

    done = run_module("--version")
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"escape {__version__}\n"
    usage = run_module("complete")  # a usage error names the command as `escape`, not __main__.py
    assert usage.returncode == 2 and usage.stderr.startswith("escape: error:") and "__main__" not in usage.stderr


def test_shell_completion_script_and_completions():
    # what `escape --show-completion` prints from bash (without a parent shell to detect)
    script = run_module(env={"_ESCAPE_COMPLETE": "source_bash"})
    assert script.returncode == 0, script.stderr
    assert "_ESCAPE_COMPLETE" in script.stdout and "complete_bash" in script.stdout
    words = run_module(env={"_ESCAPE_COMPLETE": "complete_bash", "COMP_WORDS": "escape comp", "COMP_CWORD": "1"})
    assert words.stdout.split() == ["complete"]
    options = run_module(env={"_ESCAPE_COMPLETE": "complete_bash", "COMP_WORDS": "escape complete --over",
                              "COMP_CWORD": "2"})
    assert options.stdout.split() == ["--overwrite"]
    assert "--install-completion" in run_module("--help").stdout


def _all_commands():
    import typer

    from escape_cli.cli.main import app

    root = typer.main.get_command(app)
    stack = [("escape", root)]
    while stack:
        name, command = stack.pop()
        yield name, command
        for sub_name, sub in getattr(command, "commands", {}).items():
            stack.append((f"{name} {sub_name}", sub))


def test_json_means_the_same_in_every_command():
    """--json is a flag printing JSON lines on stdout; a JSON file is --json-out PATH."""
    flags, paths = [], []
    for name, command in _all_commands():
        for param in command.params:
            if "--json" in getattr(param, "opts", []):
                assert param.is_flag, f"{name}: --json takes a value"
                flags.append(name)
            if "--json-out" in getattr(param, "opts", []):
                assert not param.is_flag, f"{name}: --json-out is a flag"
                paths.append(name)
    assert {"escape anchors", "escape complete", "escape eval", "escape dataset synth", "escape dataset info"} <= set(flags)
    assert paths == ["escape eval"]


def test_format_help_lists_every_format():
    names = ", ".join(FORMATS)
    assert {"las", "laz", "h5", "ply", "pcd", "npz"} <= set(FORMATS)
    seen = 0
    for name, command in _all_commands():
        for param in command.params:
            if {"--format", "--input-format"} & set(getattr(param, "opts", [])):
                assert names in param.help, f"{name} {param.opts[0]}: {param.help}"
                seen += 1
    assert seen >= 6


def test_format_list_matches_the_io_dispatch(tmp_path, rng):
    from escape_cli import io as cloud_io

    assert cloud_io.FORMATS == FORMATS
    cloud = rng.normal(size=(20, 3))
    for fmt in FORMATS:
        if fmt == "h5":
            pytest.importorskip("h5py")
        path = tmp_path / f"c.{fmt}"
        cloud_io.write_points(path, cloud)
        assert np.abs(cloud_io.read_points(path) - cloud).max() < 1e-5, fmt


# ---------------------------------------------------------------- the Python API takes other libraries' clouds


def test_complete_accepts_array_likes_and_returns_numpy(tiny_model, rng):
    from escape_cli import complete

    cloud = partial_cloud(rng, 300)
    reference = complete(cloud, tiny_model, output_points=500)
    for given in (cloud.tolist(), cloud.astype(np.float32), [tuple(p) for p in cloud]):
        result = complete(given, tiny_model, output_points=500)
        assert type(result.points) is np.ndarray and result.points.dtype == np.float64
        np.testing.assert_allclose(result.points, reference.points, atol=1e-5)


def test_complete_accepts_an_open3d_point_cloud(tiny_model, rng):
    open3d = pytest.importorskip("open3d")
    from escape_cli import complete

    cloud = partial_cloud(rng, 300)
    o3d_cloud = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(cloud))
    result = complete(o3d_cloud, tiny_model, output_points=500)
    assert type(result.points) is np.ndarray and type(result.is_observed) is np.ndarray
    np.testing.assert_array_equal(result.points, complete(cloud, tiny_model, output_points=500).points)


def test_complete_accepts_a_trimesh_point_cloud(tiny_model, rng):
    trimesh = pytest.importorskip("trimesh")
    from escape_cli import complete

    cloud = partial_cloud(rng, 300)
    result = complete(trimesh.PointCloud(cloud), tiny_model, output_points=500)
    assert type(result.points) is np.ndarray
    np.testing.assert_array_equal(result.points, complete(cloud, tiny_model, output_points=500).points)


def test_cloud_objects_are_duck_typed_without_importing_their_library():
    from escape_cli.core.checks import as_points

    class Vertices:  # trimesh-like
        vertices = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]

    class Points:  # open3d-like
        points = np.eye(3)

    class Method:  # a `points` method is not an array
        def points(self):
            return np.eye(3)

    assert as_points(Vertices()).shape == (2, 3) and as_points(Points()).shape == (3, 3)
    with pytest.raises(ValueError, match="must be an array of numbers"):
        as_points(Method())
    with pytest.raises(ValueError, match=r"must have shape \(N, 3\)"):
        as_points(type("Flat", (), {"points": np.zeros((4, 2))})())


# ---------------------------------------------------------------- progress on stderr, silent with -q


def test_eval_progress_and_json_keep_stdout_clean(tmp_path, tiny_model):
    from tests_support import write_tiny_pcn_tree

    write_tiny_pcn_tree(tmp_path / "tree", seed=1, objects=1)
    res = run_escape("-q", "eval", "--root", tmp_path / "tree", "--model", tiny_model, "--json", "--no-baseline")
    assert res.exit_code == 0 and res.stderr == ""
    assert json.loads(res.stdout)["average"]["count"] == 2
