"""`escape complete` batches: bad files, dead workers, resuming, file lists, shards, early checks."""

from __future__ import annotations

import json
import os
import random
from pathlib import Path

import pytest
from cli_runner import run_escape
from tests_support import partial_cloud

from escape_cli.cli.batch import plan_jobs
from escape_cli.engines.jobs import CompletionJob, complete_chunk, complete_file
from escape_cli.engines.local import WORKER_EXIT_ENV, run_local
from escape_cli.io import write_points

GOOD = ("a.ply", "b.pcd", "c.xyz", "d.ply")


@pytest.fixture
def scans(tmp_path, rng) -> Path:
    """A folder of 4 good scans."""
    folder = tmp_path / "scans"
    folder.mkdir()
    for name in GOOD:
        write_points(folder / name, partial_cloud(rng, 300))
    return folder


def complete(*args, stdin: bytes = b""):
    """Run `escape complete ... --json`; (result, JSON lines from stdout)."""
    res = run_escape("complete", *map(str, args), "--json", "--points", "400", stdin=stdin)
    assert "Traceback" not in res.stderr
    return res, [json.loads(line) for line in res.stdout.decode().splitlines()]


def by_name(lines: list[dict]) -> dict[str, dict]:
    return {Path(line["input"]).name: line for line in lines}


def test_corrupt_files_fail_alone_with_one_line_per_input(scans, tmp_path, tiny_model):
    (scans / "truncated.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    (scans / "garbage.pcd").write_bytes(b"\x00\x01 not a cloud")
    res, lines = complete(scans, "-o", tmp_path / "out", "--model", tiny_model, "--workers", "2")
    assert res.exit_code == 1
    assert sorted(by_name(lines)) == sorted([*GOOD, "truncated.ply", "garbage.pcd"])
    failed = {name for name, line in by_name(lines).items() if "error" in line}
    assert failed == {"truncated.ply", "garbage.pcd"}
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.ply", "b.ply", "c.ply", "d.ply"]
    errors = [line for line in res.stderr_lines if line.startswith("escape: error:")]
    assert errors[-1] == "escape: error: 2 of 6 file(s) failed"
    for line in errors[:-1]:  # the path once, not "x.ply: x.ply: ..."
        path = line.removeprefix("escape: error: ").split(": ")[0]
        assert line.count(path) == 1, line


def test_a_chunk_writes_what_one_file_at_a_time_writes(scans, tmp_path, tiny_model):
    """`complete_chunk` runs the network on the whole chunk at once: same bytes, same order, errors kept apart."""
    (scans / "broken.ply").write_bytes(b"not a ply")
    names = sorted(p.name for p in scans.iterdir())
    settings = CompletionJob.Settings(
        model=str(tiny_model), normalize="auto", points=400, keep_input=True, residuals=True,
        solver="batched", fmt=None, overwrite=False,
    )
    one, many = tmp_path / "one", tmp_path / "many"
    one.mkdir(), many.mkdir()
    singles = []
    for name in names:
        try:
            singles.append(complete_file(CompletionJob(str(scans / name), str(one / name)), settings))
        except Exception as err:  # noqa: BLE001 - the broken file
            singles.append({"error": str(err)})
    chunk = complete_chunk([CompletionJob(str(scans / name), str(many / name)) for name in names], settings)
    assert [Path(s["input"]).name for s in chunk] == names
    for name, single, batched in zip(names, singles, chunk):
        assert ("error" in single) == ("error" in batched), (name, batched)
        if "error" in batched:
            assert batched["error"].startswith(f"{scans / name}: ")
            continue
        assert (many / name).read_bytes() == (one / name).read_bytes()
        assert batched["observed"] == single["observed"]


def test_a_killed_worker_fails_only_its_files(scans, tmp_path, tiny_model, monkeypatch):
    monkeypatch.setenv(WORKER_EXIT_ENV, "b")  # the worker handed b.pcd exits at once
    res, lines = complete(scans, "-o", tmp_path / "out", "--model", tiny_model, "--workers", "2")
    assert res.exit_code == 1
    assert len(lines) == len(GOOD)
    assert "died" in by_name(lines)["b.pcd"]["error"]
    assert all("error" not in line for name, line in by_name(lines).items() if name != "b.pcd")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.ply", "c.ply", "d.ply"]
    assert "escape: error: 1 of 4 file(s) failed" in res.stderr_lines


def test_the_files_a_dead_worker_held_are_retried(scans, tmp_path, tiny_model, monkeypatch):
    """All four files in one chunk: the worker dies holding them; three succeed on their retry."""
    from escape_cli.cli.batch import check_model

    check_model(str(tiny_model), 1)
    monkeypatch.setenv(WORKER_EXIT_ENV, "c")
    out = tmp_path / "out"
    out.mkdir()
    jobs = [CompletionJob(str(scans / name), str(out / f"{Path(name).stem}.ply")) for name in GOOD]
    settings = CompletionJob.Settings(
        model=str(tiny_model), normalize="auto", points=400, keep_input=True, residuals=False, solver="batched",
        fmt=None, overwrite=False, threads=1,
    )
    summaries = by_name(list(run_local(jobs, settings, workers=1, chunk_size=4)))
    assert sorted(summaries) == sorted(GOOD)
    assert "died" in summaries["c.xyz"]["error"] and "retried" in summaries["c.xyz"]["error"]
    assert all(summaries[name]["points"] == 400 for name in ("a.ply", "b.pcd", "d.ply"))


def test_skip_existing_resumes_and_leaves_finished_files_alone(scans, tmp_path, tiny_model):
    out = tmp_path / "out"
    res, _ = complete(scans, "-o", out, "--model", tiny_model)
    assert res.exit_code == 0, res.stderr
    again, _ = complete(scans, "-o", out, "--model", tiny_model)  # without the flag: every file exists
    assert again.exit_code == 1 and "escape: error: 4 of 4 file(s) failed" in again.stderr_lines
    (out / "c.ply").unlink()  # as if the batch had been stopped before c
    before = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.iterdir()}

    res, lines = complete(scans, "-o", out, "--model", tiny_model, "--skip-existing", "--workers", "2")
    assert res.exit_code == 0, res.stderr
    lines = by_name(lines)
    assert {name for name, line in lines.items() if line.get("skipped")} == {"a.ply", "b.pcd", "d.ply"}
    assert lines["c.xyz"]["points"] == 400 and "skipped" not in lines["c.xyz"]
    for name, (data, mtime) in before.items():
        assert (out / name).read_bytes() == data and (out / name).stat().st_mtime_ns == mtime, name
    assert (out / "c.ply").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "no temporary left"


def test_skip_existing_does_not_take_a_broken_output_for_a_finished_one(scans, tmp_path, tiny_model):
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.ply").write_bytes(b"ply\nformat ascii 1.0\n")  # cut short by some other program
    res, lines = complete(scans, "-o", out, "--model", tiny_model, "--skip-existing")
    assert res.exit_code == 1
    assert "not a readable cloud" in by_name(lines)["a.ply"]["error"] and "--overwrite" in by_name(lines)["a.ply"]["error"]
    res, lines = complete(scans, "-o", out, "--model", tiny_model, "--skip-existing", "--overwrite")
    assert res.exit_code == 0, res.stderr
    assert by_name(lines)["a.ply"]["points"] == 400
    assert all(by_name(lines)[name].get("skipped") for name in ("b.pcd", "c.xyz", "d.ply"))


def test_skip_existing_for_a_single_file(scans, tmp_path, tiny_model):
    out = tmp_path / "one.ply"
    assert complete(scans / "a.ply", "-o", out, "--model", tiny_model)[0].exit_code == 0
    res, lines = complete(scans / "a.ply", "-o", out, "--model", tiny_model, "--skip-existing")
    assert res.exit_code == 0 and lines == [{"input": str(scans / "a.ply"), "output": str(out), "skipped": True}]


def _names(n: int) -> list[str]:
    return [f"in/scan{i:03d}.ply" for i in range(n)]


@pytest.mark.parametrize("count, shards", [(10, 3), (7, 7), (5, 8), (64, 4), (1, 2)])
def test_shards_are_disjoint_cover_the_list_and_ignore_its_order(tmp_path, count, shards):
    names = _names(count)
    listed = tmp_path / "list.txt"
    shuffled = tmp_path / "shuffled.txt"
    listed.write_text("\n".join(names) + "\n")
    mixed = names[:]
    random.Random(0).shuffle(mixed)
    shuffled.write_text("\n".join(mixed))
    parts = []
    for i in range(shards):
        plan = plan_jobs([], str(tmp_path / "out"), files_from=str(listed), shard=(i, shards))
        assert plan.batch and plan.total == count
        same = plan_jobs([], str(tmp_path / "out"), files_from=str(shuffled), shard=(i, shards))
        assert [job.source for job in same.jobs] == [job.source for job in plan.jobs]
        parts.append([job.source for job in plan.jobs])
    flat = [name for part in parts for name in part]
    assert sorted(flat) == sorted(names) and len(flat) == len(set(flat))
    assert max(map(len, parts)) - min(map(len, parts)) <= 1


def test_files_from_and_shards_through_the_command(scans, tmp_path, tiny_model):
    listed = "\n".join(str(p) for p in sorted(scans.iterdir())) + "\n\n"
    outputs = []
    for i in range(3):
        res, lines = complete("--files-from", "-", "--shard", f"{i}/3", "-o", tmp_path / "out", "--model", tiny_model,
                              stdin=listed.encode())
        assert res.exit_code == 0, res.stderr
        outputs += [line["output"] for line in lines]
    assert sorted(Path(p).name for p in outputs) == ["a.ply", "b.ply", "c.ply", "d.ply"]
    assert len(set(outputs)) == 4


def test_files_from_lists_paths_literally(tmp_path, scans, tiny_model):
    listed = tmp_path / "list.txt"
    listed.write_text(f"{scans / 'a.ply'}\n{scans / 'missing.ply'}\n{scans}\n")
    res, lines = complete("--files-from", listed, "-o", tmp_path / "out", "--model", tiny_model)
    assert res.exit_code == 1
    lines = by_name(lines)
    assert lines["a.ply"]["points"] == 400
    assert "no such file" in lines["missing.ply"]["error"] and "error" in lines["scans"]  # a folder is not expanded


@pytest.mark.parametrize("value", ["4/4", "1/0", "-1/3", "a/b", "3"])
def test_bad_shard_is_one_line(scans, tmp_path, tiny_model, value):
    res = run_escape("complete", scans, "-o", tmp_path / "out", "--model", tiny_model, "--shard", value)
    assert res.exit_code == 2 and len(res.stderr_lines) == 1 and res.stderr.startswith("escape: error: --shard:")
    assert not (tmp_path / "out").exists()


def _unwritable_folder(tmp_path) -> Path:
    """A folder this process cannot create files in, or skip where there is none (root ignores chmod)."""
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o500)
    candidates = [folder, Path("/sys")]
    for candidate in candidates:
        try:
            (candidate / "probe.tmp").touch()
            (candidate / "probe.tmp").unlink()
        except OSError:
            return candidate
    pytest.skip("no folder here that this user cannot write to")


@pytest.mark.parametrize("kind", ["locked", "a file", "under a file"])
def test_an_unwritable_output_folder_is_reported_before_any_work(scans, tmp_path, tiny_model, kind):
    (scans / "broken.ply").write_bytes(b"not a ply")  # would be reported if anything were read
    if kind == "locked":
        out = _unwritable_folder(tmp_path)
    elif kind == "a file":
        out = tmp_path / "taken"
        out.write_text("x")
    else:
        (tmp_path / "file").write_text("x")
        out = tmp_path / "file" / "out"
    try:
        for source, target in ((scans, out), (scans / "a.ply", out / "one.ply")):  # a batch, one file
            res = run_escape("complete", source, "-o", target, "--model", tiny_model, "--json")
            assert res.exit_code == 1 and len(res.stderr_lines) == 1, res.stderr
            assert res.stderr.startswith("escape: error: cannot ") and res.stdout == b""
    finally:
        if kind == "locked" and out.parent == tmp_path:
            out.chmod(0o700)


@pytest.mark.parametrize("kind", ["missing", "folder", "not onnx"])
def test_an_unusable_model_is_reported_before_any_work(scans, tmp_path, kind):
    model = tmp_path / "m.onnx"
    if kind == "folder":
        model.mkdir()
    elif kind == "not onnx":
        model.write_bytes(b"garbage")
        (tmp_path / "m.json").write_text(json.dumps({"k": 8, "input_points": 256, "output_points": 256}))
    for source, out in ((scans, tmp_path / "out"), (scans / "a.ply", tmp_path / "one.ply")):  # a batch, one file
        res = run_escape("complete", source, "-o", out, "--model", model, "--json")
        assert res.exit_code == 1 and len(res.stderr_lines) == 1 and res.stdout == b"", res.stderr
        assert "model" in res.stderr and ("folder" in res.stderr or kind != "folder")
        assert not out.exists()


def test_single_file_errors_name_the_path_once(tmp_path, tiny_model):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\n")
    res = run_escape("complete", bad, "-o", tmp_path / "o.ply", "--model", tiny_model)
    assert res.exit_code == 1 and len(res.stderr_lines) == 1
    assert res.stderr_lines[0].count(str(bad)) == 1, res.stderr


def test_engine_and_ray_address_options(scans, tmp_path, tiny_model):
    res = run_escape("complete", scans, "-o", tmp_path / "out", "--model", tiny_model, "--engine", "spark")
    assert res.exit_code == 2 and res.stderr_lines == ["escape: error: --engine: must be local or ray (see --help)"]
    res = run_escape("complete", scans, "-o", tmp_path / "out", "--model", tiny_model, "--ray-address", "auto")
    assert res.exit_code == 2 and "--ray-address: needs --engine ray" in res.stderr
    res = run_escape("complete", "-o", tmp_path / "out", "--model", tiny_model)
    assert res.exit_code == 2 and len(res.stderr_lines) == 1 and "--files-from" in res.stderr


def test_an_empty_shard_does_nothing(scans, tmp_path, tiny_model):
    res, lines = complete(scans / "a.ply", "--shard", "1/2", "-o", tmp_path / "out", "--model", tiny_model)
    assert res.exit_code == 0 and lines == [] and not os.listdir(tmp_path / "out")


def test_workers_that_die_as_they_start_stop_the_batch(scans, tmp_path, tiny_model, monkeypatch):
    """A broken environment (here: every file kills its worker) ends with every file failed, not a hang."""
    from escape_cli.engines import local

    monkeypatch.setattr(local, "STARTUP_DEATHS", 2)
    out = tmp_path / "out"
    out.mkdir()
    monkeypatch.setenv(WORKER_EXIT_ENV, "a")
    jobs = [CompletionJob(str(scans / "a.ply"), str(out / "a.ply"))] * 5
    settings = CompletionJob.Settings(
        model=str(tiny_model), normalize="auto", points=400, keep_input=True, residuals=False, solver="batched",
        fmt=None, overwrite=False, threads=1,
    )
    summaries = list(run_local(jobs, settings, workers=1, chunk_size=1))
    assert len(summaries) == 5 and all("die as they start" in s["error"] or "died" in s["error"] for s in summaries)
    assert sum("die as they start" in s["error"] for s in summaries) >= 3


NOT_CLOUDS = {
    "LICENSE": "MIT License\n\nPermission is hereby granted, free of charge\n",
    "LICENSE_PCL.txt": "Software License Agreement (BSD License)\n\nCopyright (c) 2009, Willow Garage\n",
    "README.txt": "Scans of the lab\nTaken in May\n",
    "notes.md": "# notes\n",
    "meta.json": "{}\n",
}


def test_a_folder_gives_only_its_point_clouds(scans, tmp_path, tiny_model):
    """Files of unknown extensions and text files that are no clouds are skipped, counted with -v."""
    for name, text in NOT_CLOUDS.items():
        (scans / name).write_text(text)
    (scans / "table.txt").write_text("# x y z\n0 0 0\n1 0 0\n" + "".join(f"{i % 7} {i % 5} {i % 3}\n" for i in range(40)))
    res = run_escape("-v", "complete", scans, "-o", tmp_path / "out", "--model", tiny_model, "--points", "400", "--json")
    assert res.exit_code == 0, res.stderr
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.ply", "b.ply", "c.ply", "d.ply", "table.ply"]
    skipped = ", ".join(sorted(NOT_CLOUDS))
    assert f"escape: INFO: {scans}: skipped 5 file(s) that are not point clouds ({skipped})" in res.stderr_lines
    quiet = run_escape("complete", scans, "-o", tmp_path / "again", "--model", tiny_model, "--points", "400", "--json")
    assert quiet.exit_code == 0 and "skipped" not in quiet.stderr  # a -v line


@pytest.mark.parametrize("how", ["named", "glob"])
def test_files_named_or_globbed_are_read_whatever_they_are_called(scans, tmp_path, tiny_model, how):
    (scans / "LICENSE_PCL.txt").write_text(NOT_CLOUDS["LICENSE_PCL.txt"])
    inputs = [scans / "a.ply", scans / "LICENSE_PCL.txt"] if how == "named" else [f"{scans}/*.*"]
    res, lines = complete(*inputs, "-o", tmp_path / "out", "--model", tiny_model)
    assert res.exit_code == 1
    assert by_name(lines)["LICENSE_PCL.txt"]["error"].endswith("line 1: 'Software' is not a number")
    assert "a.ply" in os.listdir(tmp_path / "out")
