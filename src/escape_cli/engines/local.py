"""The local batch engine: worker processes that load the model once and complete chunks of jobs.

The parent hands each worker one chunk at a time over its own pipe and waits on the
pipes and on the processes themselves, so it always knows which files a worker holds.
A worker that dies (killed, out of memory, a crash in a native library) fails only
those files: they are retried one by one in a fresh worker, and a file whose worker
dies again is reported as failed. Nothing waits on a dead process, so a batch always
returns.

Test hook: with ``ESCAPE_TEST_WORKER_EXIT=STEM`` in the environment, a worker handed a
chunk holding an input named STEM.* exits at once (``os._exit(3)``), as a killed
worker would.
"""

from __future__ import annotations

import logging
import os
import signal
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import escape_cli.interrupts as interrupts
from escape_cli.engines.jobs import CompletionJob, complete_chunk, failure, warm_model
from escape_cli.piped_process import PipedProcess

log = logging.getLogger("escape")

STARTUP_DEATHS = 3
"""Workers in a row that die before answering at all: then the environment is broken, and the batch stops."""
CHUNK_FILES = 8
"""The most files handed to a worker at once (a dead worker loses at most this many, then retries them)."""
WORKER_EXIT_ENV = "ESCAPE_TEST_WORKER_EXIT"


def chunk_size_for(n_jobs: int, workers: int) -> int:
    """Files per chunk: up to `CHUNK_FILES`, small enough that every worker gets about 4 chunks."""
    return max(1, min(CHUNK_FILES, n_jobs // (4 * max(1, workers))))


def run_local(jobs: list[CompletionJob], settings: CompletionJob.Settings, *, workers: int, chunk_size: int | None = None):
    """Complete `jobs` in `workers` processes; yields one summary per job as chunks finish.

    Parameters
    ----------
    jobs : list of CompletionJob
    settings : CompletionJob.Settings
        `settings.threads` is each worker's onnxruntime thread count.
    workers : int
        Worker processes (at least 1).
    chunk_size : int, optional
        Files per chunk (default `chunk_size_for`).

    Yields
    ------
    dict
        Summaries, in the order the chunks finish (not the order of `jobs`).
    """
    import multiprocessing
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()  # now: starting it unblocks SIGINT, undoing `interrupts.deferred` around a worker's start
    size = chunk_size or chunk_size_for(len(jobs), workers)
    queue = deque(_Task(tuple(jobs[i : i + size]), retry=False) for i in range(0, len(jobs), size))
    context = multiprocessing.get_context("spawn")
    level = logging.getLogger("escape").getEffectiveLevel()
    pool: list[_Worker] = []
    deaths = _StartupDeaths()
    folders = output_folders(jobs)
    finished = False
    try:
        with interrupts.on_interrupt(lambda: _abandon(pool, folders)):
            while queue or _busy(pool):
                for worker in pool:
                    if worker.task is None and queue:
                        worker.give(queue.popleft())
                while queue and len(pool) < workers:
                    with interrupts.deferred():  # see there: Ctrl-C is the parent's alone
                        worker = _Worker(context, settings, level)
                        pool.append(worker)
                    worker.give(queue.popleft())
                yield from _collect(pool, queue, deaths, folders)
                if deaths.broken:
                    yield from _give_up(pool, queue, deaths.broken)
            finished = True
    finally:
        for worker in pool:
            worker.stop(gently=finished)


def output_folders(jobs: list[CompletionJob]) -> set[Path]:
    """The folders the jobs write into (where a stopped worker may leave a temporary file)."""
    return {Path(path).parent for job in jobs for path in (job.output, job.anchors) if path is not None}


def _abandon(pool: list[_Worker], folders: set[Path]) -> None:
    """On Ctrl-C or SIGTERM: kill every worker, then remove what they were writing.

    Their finished outputs are whole (renamed into place); a half-written one is a
    temporary file named with the worker's process id, in an output folder.
    """
    for worker in pool:
        worker.process.kill()
    for worker in pool:
        worker.process.join()
    _remove_temporary_files(folders, [worker.process.pid for worker in pool])


def _remove_temporary_files(folders: set[Path], pids: list[int]) -> None:
    from escape_cli.io.files import remove_temporary_files

    for folder in folders:
        remove_temporary_files(folder, pids=pids)


class _StartupDeaths:
    """Counts workers in a row that died before their first answer."""

    def __init__(self):
        self.count = 0
        self.broken: str | None = None  # set to the reason once STARTUP_DEATHS is reached

    def record(self, worker: _Worker, how: str) -> None:
        self.count = 0 if worker.answered else self.count + 1
        if self.count >= STARTUP_DEATHS:
            self.broken = f"worker processes die as they start ({how}, {self.count} in a row)"


def _give_up(pool: list[_Worker], queue: deque, reason: str):
    """Fail every file still held or queued with `reason`."""
    log.error("%s; giving up the remaining files", reason)
    for worker in _busy(pool):
        yield from (failure(job, reason) for job in worker.task.jobs)
        worker.task = None
    while queue:
        yield from (failure(job, reason) for job in queue.popleft().jobs)


@dataclass(frozen=True)
class _Task:
    jobs: tuple[CompletionJob, ...]
    retry: bool  # a retry after a dead worker: one file, and no second retry


class _Worker(PipedProcess):
    """One worker process, its end of the pipe, and the task it holds (None when idle)."""

    def __init__(self, context, settings, level: int):
        conn, child = context.Pipe(duplex=True)
        super().__init__(conn, context.Process(target=_serve, args=(child, settings, level), daemon=True))
        self.process.start()
        child.close()
        self.task: _Task | None = None
        self.answered = False  # it has sent back at least one chunk

    def give(self, task: _Task) -> None:
        self.task = task
        self.send(task.jobs)

    def receive(self) -> list[dict] | None:
        """The summaries of the task it held, or None when it died."""
        results = self.answer()
        if results is not None:
            self.answered = True
        return results


def _busy(pool: list[_Worker]) -> list[_Worker]:
    return [worker for worker in pool if worker.task is not None]


def _collect(pool: list[_Worker], queue: deque, deaths: _StartupDeaths, folders: set[Path]):
    """Wait until a busy worker answers or dies; yield what came back, requeue or fail a dead one's files
    (and remove what it was writing)."""
    from multiprocessing.connection import wait

    busy = _busy(pool)
    ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
    for worker in busy:
        if worker.conn not in ready and worker.process.sentinel not in ready:
            continue
        results = worker.receive()
        if results is not None:
            worker.task = None
            deaths.count = 0
            yield from results
            continue
        pool.remove(worker)
        task, how = worker.task, worker.death()
        _remove_temporary_files(folders, [worker.process.pid])
        deaths.record(worker, how)
        if task.retry:  # its error line says so
            yield from (failure(job, f"the worker completing it died ({how}), also when retried in a fresh worker") for job in task.jobs)
        else:
            names = ", ".join(job.source for job in task.jobs)
            log.warning("a worker died (%s) holding %s; retrying in a fresh worker, one file at a time", how, names)
            queue.extendleft(_Task((job,), retry=True) for job in reversed(task.jobs))


def _serve(conn, settings: CompletionJob.Settings, level: int) -> None:
    """A worker process: load the model once, then complete the chunks that come, until None."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle (it was blocked until now)
    logging.basicConfig(level=level, format="escape: %(levelname)s: %(message)s")
    warm_model(settings)
    exit_stem = os.environ.get(WORKER_EXIT_ENV)
    while True:
        try:
            jobs = conn.recv()
        except (EOFError, OSError):  # the parent is gone
            return
        if jobs is None:
            return
        if exit_stem and any(Path(job.source).stem == exit_stem for job in jobs):
            os._exit(3)
        conn.send(complete_chunk(jobs, settings))

