"""The Ray Data batch engine: the same jobs as the local engine, on this machine or a Ray cluster.

Ray's reader (`ray.data.read_binary_files`) reads the inputs; a pool of actors, each
with the model loaded once, completes them a chunk at a time through
`engines.jobs.complete_chunk` and writes the outputs with the same atomic writer and
names as the local engine; the JSON summaries stream back to the driver as the chunks
finish. On a cluster the inputs, the outputs and the model must be on a file system
that every node mounts at the same path, and escape-cli must be installed on every
node: each actor works in the driver's current folder, so relative paths mean the same
everywhere and the outputs are byte-identical to ``--engine local``.

This is the only module that imports ray.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import warnings
from pathlib import Path

import escape_cli.interrupts as interrupts
from escape_cli.engines.jobs import CompletionJob, complete_chunk, failure, warm_model
from escape_cli.errors import EscapeError

log = logging.getLogger("escape")

CHUNK_FILES = 8
"""Files per actor call: the batch of scans a call completes."""


def run_ray(jobs: list[CompletionJob], settings: CompletionJob.Settings, *, actors: int, address: str | None = None,
            chunk_size: int = CHUNK_FILES):
    """Complete `jobs` on Ray Data with `actors` actors; yields one summary per job as chunks finish.

    Parameters
    ----------
    jobs : list of CompletionJob
    settings : CompletionJob.Settings
        `settings.threads` is each actor's onnxruntime thread count (each actor asks
        Ray for one CPU).
    actors : int
        Actors in the pool, each with its own model.
    address : str, optional
        A running Ray cluster (``auto``, ``ray://host:10001``, ``host:6379``). None
        uses the Ray this process is already connected to, else starts a local one with
        this machine's CPUs (and shuts it down at the end).
    chunk_size : int
        Files per actor call.

    Yields
    ------
    dict
        Summaries, in the order the chunks finish.
    """
    ray = _import_ray()
    own = not ray.is_initialized()  # this call starts (or joins) Ray, and stops (or leaves) it
    with interrupts.on_interrupt(lambda: _abandon(ray, own, jobs)):  # from the start of ray.init on
        _connect(ray, address)
        try:
            yield from _run(ray, jobs, settings, actors, chunk_size)
        finally:
            if own:
                with interrupts.deferred():  # an interrupt now waits: cut short, a shutdown leaves Ray's agents running
                    ray.shutdown()


def _abandon(ray, own: bool, jobs: list[CompletionJob]) -> None:
    """On Ctrl-C or SIGTERM: stop the Ray this command started (its actors with it; also half-started),
    then remove the temporary files of outputs that actors were writing (any process's: actors' ids are Ray's)."""
    from escape_cli.io.files import remove_temporary_files

    if own and ray.is_initialized():
        saved = _silence_stderr()  # Ray's native code reports the actors it loses there while it stops
        try:
            ray.shutdown()
        finally:
            _restore_stderr(saved)
    names: dict[Path, set[str]] = {}
    for job in jobs:
        for path in (job.output, job.anchors):
            if path is not None:
                names.setdefault(Path(path).parent, set()).add(Path(path).name)
    for folder, inside in names.items():
        remove_temporary_files(folder, names=inside)


def _silence_stderr() -> int | None:
    """Point descriptor 2 at /dev/null; returns a copy of what it was (None if that failed)."""
    try:
        saved = os.dup(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        return None
    os.dup2(devnull, 2)
    os.close(devnull)
    return saved


def _restore_stderr(saved: int | None) -> None:
    if saved is not None:
        os.dup2(saved, 2)
        os.close(saved)


def _import_ray():
    try:
        import ray
        import ray.data
    except ImportError:
        raise EscapeError("--engine ray needs Ray Data: pip install 'escape-cli[ray]'") from None
    return ray


def _connect(ray, address: str | None) -> None:
    """Join or start Ray, unless this process is connected already."""
    if ray.is_initialized():
        return
    quiet = {"log_to_driver": False, "logging_level": _ray_log_level(), "include_dashboard": False}
    try:
        if address is None:
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # a local run reports nothing to anyone
            ray.init(address="local", num_cpus=os.cpu_count() or 1, **quiet)
        else:
            ray.init(address=address, **quiet)
    except (ConnectionError, ValueError, RuntimeError) as err:
        where = f"the Ray cluster at {address}" if address else "a local Ray"
        raise EscapeError(f"cannot start or reach {where}: {' '.join(str(err).split())}") from None
    except SystemExit as exit_:  # ray.init's own SIGTERM handler (sys.exit(15)) while Ray starts
        if interrupts.installed() and exit_.code == signal.SIGTERM:
            interrupts.interrupt(signal.SIGTERM)
        raise
    finally:
        if interrupts.installed():
            interrupts.install()  # ray.init leaves its SIGTERM handler in place of the command's


def _ray_log_level() -> int:
    """Ray's own log level: silent (escape reports its errors in one line), warnings with -v, all with -vv."""
    level = logging.getLogger("escape").getEffectiveLevel()
    return logging.CRITICAL if level >= logging.WARNING else (logging.WARNING if level >= logging.INFO else logging.INFO)


def _one_line(err: Exception) -> str:
    """A Ray exception as one short line: no colour codes, no traceback."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(err))
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.strip().startswith(("^", "File "))]
    head = lines[0] if lines else ""
    cause = next((line for line in reversed(lines) if re.match(r"\w+(Error|Exception):", line)), "")
    message = f"{type(err).__name__}: {head}" + (f" ({cause})" if cause and cause not in head else "")
    return message if len(message) <= 400 else message[:397] + "..."


def _run(ray, jobs, settings, actors: int, chunk_size: int):
    import numpy as np
    from ray.data import ActorPoolStrategy, DataContext

    cwd = os.getcwd()
    pending = []
    for job in jobs:
        if os.path.isfile(job.source) and os.access(job.source, os.R_OK):
            pending.append(job)
        else:  # Ray's reader would fail the whole dataset: report it here, as the local engine does
            yield from complete_chunk([job], settings)
    if not pending:
        return
    paths = [os.path.join(cwd, job.source) for job in pending]  # what Ray's reader reports back
    table = ray.put(_job_table(paths, pending))
    logging.getLogger("ray.data").setLevel(_ray_log_level())
    context = DataContext.get_current()
    saved = context.enable_progress_bars, context.max_errored_blocks
    context.enable_progress_bars = False
    context.max_errored_blocks = -1  # a failed chunk loses its files (reported below), not the run
    try:
        with warnings.catch_warnings():
            # max_restarts=0: an actor that dies is not restarted to retry the same chunk
            # forever; Ray Data takes its remote arguments this way up to 2.63.
            warnings.simplefilter("ignore", DeprecationWarning)
            dataset = ray.data.read_binary_files(paths, include_paths=True, num_cpus=0).map_batches(
                _Completer,
                batch_size=chunk_size,
                batch_format="numpy",
                compute=ActorPoolStrategy(size=actors),
                num_cpus=1,
                fn_constructor_kwargs={"settings": settings, "table": [table], "cwd": cwd},
                max_restarts=0,
            )
        reported = set()
        for batch in dataset.iter_batches(batch_size=None, batch_format="numpy"):
            for line in np.asarray(batch["summary"]).tolist():
                summary = json.loads(line)
                reported.add(summary["input"])
                yield summary
    except EscapeError:
        raise
    except Exception as err:  # Ray's own failures: one line, not a traceback
        raise EscapeError(f"the Ray run failed: {_one_line(err)}") from None
    finally:
        context.enable_progress_bars, context.max_errored_blocks = saved
    for job in pending:
        if job.source not in reported:
            yield failure(job, "no result came back from Ray (the actor completing it failed)")


def _job_table(paths: list[str], jobs: list[CompletionJob]) -> dict:
    """Jobs by reader path, as sorted byte-string arrays (shared by the actors without copies)."""
    import numpy as np

    keys = np.array([os.fsencode(p) for p in paths])
    order = np.argsort(keys, kind="stable")

    def column(values):
        return np.array([os.fsencode(value or "") for value in values])[order]

    return {
        "keys": keys[order],
        "sources": column(job.source for job in jobs),
        "outputs": column(job.output for job in jobs),
        "anchors": column(job.anchors for job in jobs),
    }


class _Completer:
    """A Ray actor: works in the driver's folder, loads the model once, completes chunks of files."""

    def __init__(self, settings: CompletionJob.Settings, table: list, cwd: str):
        import ray

        logging.basicConfig(level=logging.WARNING, format="escape: %(levelname)s: %(message)s")
        try:
            os.chdir(cwd)
        except OSError:
            raise EscapeError(
                f"this Ray node has no folder {cwd}: inputs and outputs must be on a file system every node mounts there"
            ) from None
        self.settings = settings
        self.table = ray.get(table[0])
        warm_model(settings)

    def _job(self, path: str) -> CompletionJob:
        import numpy as np

        t = self.table
        i = int(np.searchsorted(t["keys"], os.fsencode(path)))
        anchors = os.fsdecode(t["anchors"][i])
        return CompletionJob(os.fsdecode(t["sources"][i]), os.fsdecode(t["outputs"][i]), anchors or None)

    def __call__(self, batch: dict) -> dict:
        import numpy as np

        jobs = [self._job(path) for path in np.asarray(batch["path"]).tolist()]
        summaries = complete_chunk(jobs, self.settings, data=list(batch["bytes"]))
        return {"summary": np.array([json.dumps(summary) for summary in summaries], dtype=object)}
