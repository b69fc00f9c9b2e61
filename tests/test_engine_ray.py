"""`escape complete --engine ray` on a local Ray with 2 CPUs: the same bytes and reports as the local engine."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from cli_runner import run_escape
from tests_support import partial_cloud

from escape_cli.io import write_points

ray = pytest.importorskip("ray", reason="the ray extra (escape-cli[ray]) is not installed")


@pytest.fixture(scope="module")
def local_ray():
    """A new local Ray with 2 CPUs for this module's tests (never a cluster found here), shut down after them."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    yield
    ray.shutdown()


@pytest.fixture
def scans(tmp_path, rng) -> Path:
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in ("a.ply", "b.pcd", "c.xyz", "d.npy", "e.ply"):
        write_points(folder / name, partial_cloud(rng, 300))
    (folder / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    (folder / "empty.pcd").write_bytes(b"")
    return folder


def run(scans: Path, out: Path, model: Path, *options: str):
    res = run_escape("complete", scans, "-o", out, "--model", model, "--json", "--points", "500", "--residuals",
                     "--anchors-out", out.with_name(out.name + "-anchors"), *options)
    assert "Traceback" not in res.stderr
    lines = {Path(line["input"]).name: line for line in map(json.loads, res.stdout.decode().splitlines())}
    return res, lines


def comparable(line: dict) -> dict:
    return {key: value for key, value in line.items() if key not in ("seconds", "output")}


def folder_bytes(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_ray_writes_the_same_bytes_and_isolates_bad_files(local_ray, scans, tmp_path, tiny_model):
    local, local_lines = run(scans, tmp_path / "local", tiny_model, "--workers", "2")
    remote, ray_lines = run(scans, tmp_path / "ray", tiny_model, "--engine", "ray", "--workers", "2")
    assert local.exit_code == remote.exit_code == 1
    assert sorted(ray_lines) == sorted(local_lines) == sorted(p.name for p in scans.iterdir())
    assert {name: comparable(line) for name, line in ray_lines.items()} == {
        name: comparable(line) for name, line in local_lines.items()
    }
    assert {name for name, line in ray_lines.items() if "error" in line} == {"broken.ply", "empty.pcd"}
    assert folder_bytes(tmp_path / "ray") == folder_bytes(tmp_path / "local")
    assert len(folder_bytes(tmp_path / "ray")) == 5
    assert folder_bytes(tmp_path / "ray-anchors") == folder_bytes(tmp_path / "local-anchors")
    def errors(res):
        return sorted(line for line in res.stderr_lines if line.startswith("escape: error:"))

    assert errors(remote) == errors(local)


def test_ray_skip_existing_and_shards(local_ray, scans, tmp_path, tiny_model):
    out = tmp_path / "out"
    first, lines = run(scans, out, tiny_model, "--engine", "ray", "--workers", "1", "--shard", "0/2")
    assert first.exit_code in (0, 1) and len(lines) == 4  # 7 inputs: shard 0 of 2 holds 4
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    again, lines = run(scans, out, tiny_model, "--engine", "ray", "--workers", "1", "--skip-existing")
    assert again.exit_code == 1 and len(lines) == 7  # broken.ply and empty.pcd fail again
    done = {Path(line["output"]).name for line in lines.values() if line.get("skipped")}
    assert done == set(before)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir() if p.name in before} == before
    assert len(list(out.iterdir())) == 5
