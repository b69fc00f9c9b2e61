"""The dataset commands' worker processes (escape_cli.data.workers): results, dead workers, errors, interrupts."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from escape_cli.data.workers import run_in_workers
from escape_cli.errors import DatasetError
from tests_support import worker_job

TESTS = Path(__file__).resolve().parent


def _folders(job):
    return [Path(job[0])]


def test_every_result_once_with_or_without_workers(tmp_path):
    jobs = [(str(tmp_path), n, "ok") for n in range(7)]
    assert list(run_in_workers(worker_job, jobs, 1)) == [n * n for n in range(7)]
    assert sorted(run_in_workers(worker_job, jobs, 2, folders_of=_folders)) == [n * n for n in range(7)]
    assert not list(tmp_path.iterdir())


def test_a_dead_worker_fails_its_job_alone_and_leaves_no_temporary_file(tmp_path):
    jobs = [(str(tmp_path), n, "die" if n == 2 else "ok") for n in range(5)]
    results = list(run_in_workers(worker_job, jobs, 2, folders_of=_folders, on_death=lambda job, how: (job[1], how)))
    assert sorted(r for r in results if isinstance(r, int)) == [0, 1, 9, 16]  # a fresh worker took the rest
    assert [r for r in results if not isinstance(r, int)] == [(2, "exit code 3")]
    assert not list(tmp_path.iterdir())
    with pytest.raises(DatasetError, match=r"a worker process died \(exit code 3\)"):
        list(run_in_workers(worker_job, jobs, 2, folders_of=_folders))
    assert not list(tmp_path.iterdir())


def test_an_error_in_a_job_is_raised_in_the_caller(tmp_path):
    jobs = [(str(tmp_path), n, "raise" if n == 1 else "ok") for n in range(3)]
    with pytest.raises(ValueError, match="job 1 failed"):
        list(run_in_workers(worker_job, jobs, 2, folders_of=_folders))
    assert not list(tmp_path.iterdir())  # the other workers were stopped, and what they wrote removed


DRIVER = """
import escape_cli.interrupts as interrupts
interrupts.install()
import sys
sys.path.insert(0, sys.argv[1])
from escape_cli.data.workers import run_in_workers
from tests_support import worker_job
from pathlib import Path
jobs = [(sys.argv[2], n, "sleep") for n in range(4)]
for _ in run_in_workers(worker_job, jobs, 2, folders_of=lambda job: [Path(job[0])]):
    pass
"""


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="reads the workers' state from /proc")
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupt_kills_the_workers_and_removes_what_they_were_writing(tmp_path, signum):
    from test_cli_promises import _alive, _children

    process = subprocess.Popen([sys.executable, "-c", DRIVER, str(TESTS), str(tmp_path)], stderr=subprocess.PIPE,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        started = [process.stderr.readline(), process.stderr.readline()]
        assert all(line.startswith(b"job ") for line in started), started
        assert len(list(tmp_path.glob("*.tmp"))) == 2  # each worker holds one half-written file
        workers = [pid for pid in _children(process.pid) if b"spawn_main" in Path(f"/proc/{pid}/cmdline").read_bytes()]
        process.send_signal(signum)  # to the parent alone, as `kill` or a scheduler sends it
        _, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 128 + signum
    assert err == b"escape: interrupted\n"
    assert not list(tmp_path.iterdir())
    assert len(workers) == 2
    time.sleep(0.1)
    assert not [pid for pid in workers if _alive(pid)]
