"""Worker processes of the dataset commands (`dataset synth`, `dataset from-shapes`).

`run_in_workers(function, jobs, workers)` yields ``function(job)`` for every job, in
the order they finish, from `workers` spawned processes whose numeric libraries use one
thread each (one job at a time over one pipe per worker). As in the completion
engine (`engines.local`), the workers start with SIGINT blocked (`interrupts.deferred`),
so a Ctrl-C at the terminal reaches the parent alone; on Ctrl-C or SIGTERM the parent
kills them and removes the temporary files they were writing (named with their process
id, `io.files.temporary_name`, in the folders `folders_of(job)` names), and nothing
they print follows the one line `escape: interrupted`. A worker that dies (killed, out
of memory) fails the job it held (`on_death`), and a fresh one takes its place; the
run never waits on a dead worker.
"""

from __future__ import annotations

import os
import signal
from collections import deque
from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

import escape_cli.interrupts as interrupts
from escape_cli.errors import DatasetError
from escape_cli.piped_process import PipedProcess

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def run_in_workers(function: Callable, jobs: Sequence, workers: int, *,
                   folders_of: Callable[[object], Iterable[Path]] | None = None,
                   on_death: Callable[[object, str], object] | None = None) -> Iterator:
    """``function(job)`` for every job, as each finishes; in this process when `workers` is 1.

    Parameters
    ----------
    function : a module-level function (it is pickled by reference)
    jobs : sequence of picklable jobs
    workers : int
    folders_of : callable, optional
        The folders a job writes into: where a killed worker's temporary files are removed.
    on_death : callable, optional
        ``on_death(job, how)``: the result of a job whose worker died (default: DatasetError).
    """
    if workers <= 1:
        yield from map(function, jobs)
        return
    import multiprocessing
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()  # now: starting it unblocks SIGINT, undoing `interrupts.deferred`
    context = multiprocessing.get_context("spawn")
    queue = deque(jobs)
    pool: list[_Worker] = []
    finished = False
    try:
        with interrupts.on_interrupt(lambda: _abandon(pool, folders_of)):
            while queue or any(w.job is not None for w in pool):
                while queue and len(pool) < min(workers, len(jobs)):
                    pool.append(_Worker.start(context, function))
                for worker in pool:
                    if worker.job is None and queue:
                        worker.give(queue.popleft())
                yield from _collect(pool, folders_of, on_death)
            finished = True
    finally:
        if not finished:  # an error or an early close: what the workers were writing goes too
            _abandon(pool, folders_of)
        for worker in pool:
            worker.stop(gently=finished)


class _Worker(PipedProcess):
    """One worker process, its end of the pipe, and the job it holds (None when idle)."""

    def __init__(self, conn, process):
        super().__init__(conn, process)
        self.job = None

    @classmethod
    def start(cls, context, function: Callable) -> "_Worker":
        saved = {key: os.environ.get(key) for key in THREAD_VARIABLES}
        os.environ.update({key: "1" for key in THREAD_VARIABLES})  # one thread per worker process
        try:
            with interrupts.deferred():  # Ctrl-C is the parent's alone, also while the worker starts
                conn, child = context.Pipe(duplex=True)
                process = context.Process(target=_serve, args=(child, function), daemon=True)
                process.start()
                child.close()
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
        return cls(conn, process)

    def give(self, job) -> None:
        self.job = job
        self.send(job)

    def receive(self):
        """(kind, value) of the job it held, or None when it died."""
        return self.answer()


def _collect(pool: list[_Worker], folders_of, on_death) -> Iterator:
    """Wait until a busy worker answers or dies; yield its result (a dead one's: `on_death`'s), raise its error."""
    from multiprocessing.connection import wait

    busy = [w for w in pool if w.job is not None]
    ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
    for worker in busy:
        if worker.conn not in ready and worker.process.sentinel not in ready:
            continue
        answer = worker.receive()
        job, worker.job = worker.job, None
        if answer is not None:
            kind, value = answer
            if kind == "raise":
                raise value
            yield value
            continue
        pool.remove(worker)
        how = worker.death()
        _remove_temporary_files([(worker.process.pid, job)], folders_of)
        if on_death is None:
            raise DatasetError(f"a worker process died ({how})")
        yield on_death(job, how)


def _abandon(pool: list[_Worker], folders_of) -> None:
    """On Ctrl-C or SIGTERM: kill every worker, then remove what they were writing."""
    for worker in pool:
        worker.process.kill()
    for worker in pool:
        worker.process.join()
    _remove_temporary_files([(w.process.pid, w.job) for w in pool if w.job is not None], folders_of)


def _remove_temporary_files(held: list[tuple[int, object]], folders_of) -> None:
    if folders_of is None:
        return
    from escape_cli.io.files import remove_temporary_files

    for pid, job in held:
        for folder in set(folders_of(job)):
            remove_temporary_files(folder, pids=[pid])


def _serve(conn, function: Callable) -> None:
    """A worker process: run the jobs that come, until None (or the parent's end closes)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle (it was blocked until now)
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            answer = ("ok", function(job))
        except Exception as err:  # a bug: the parent raises it
            answer = ("raise", err)
        try:
            conn.send(answer)
        except (OSError, ValueError):  # the parent has gone
            return
        except Exception as err:  # noqa: BLE001 (an unpicklable result or error)
            conn.send(("raise", RuntimeError(f"{type(err).__name__}: {err}")))


__all__ = ["run_in_workers"]
