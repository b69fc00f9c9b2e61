"""What every batch engine runs: completion jobs (read, complete, write one file) and their summaries.

A summary is the dict printed as one JSON line per input: the completion's numbers, or
``{"input", "output", "skipped": true}`` for a file finished before (``skip_existing``),
or ``{"input", "error"}``. Engines call `complete_chunk`; nothing here raises for a
file's problem.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

from escape_cli.errors import (
    EscapeError,
    InputFileError,
    OutputExistsError,
    about,
    errors_about,
)
from escape_cli.formats import FIELDLESS_FORMATS, residuals_refusal


@dataclass(frozen=True)
class CompletionJob:
    """One input file and where its results go (`anchors`: None for no anchors file)."""

    source: str
    output: str
    anchors: str | None = None

    @dataclass(frozen=True)
    class Settings:
        """How every file of a batch is completed and written (the `escape complete` options)."""

        model: str | None
        normalize: str
        points: int
        keep_input: bool
        residuals: bool
        solver: str
        fmt: str | None
        overwrite: bool
        input_format: str | None = None
        threads: int = 0
        snap_radius: float | None = None
        skip_existing: bool = False
        anchor_sets: int = 1


Settings = CompletionJob.Settings


def complete_chunk(jobs, settings: Settings, data=None) -> list[dict]:
    """Complete several files with one batched network call; one summary each, in the order of `jobs`.

    Each file is read (and its outputs checked) on its own, the scans that read go
    through `pipeline.complete_many` together, and each result is written on its own:
    the outputs are those `complete_file` writes, byte for byte.

    Parameters
    ----------
    jobs : sequence of CompletionJob
    settings : CompletionJob.Settings
    data : sequence of bytes, optional
        Each source's bytes, already read by the engine; None reads the files.

    Returns
    -------
    list of dict
        A file's problem is its summary's ``"error"``; this never raises for one.
    """
    jobs = list(jobs)
    blobs = [None] * len(jobs) if data is None else list(data)
    summaries: list[dict | None] = [None] * len(jobs)
    ready = []  # (position, targets, cloud, start time)
    for position, (job, blob) in enumerate(zip(jobs, blobs)):
        start = time.perf_counter()
        targets = _guarded(job, lambda: outputs_to_write(job, settings))
        if isinstance(targets, dict):
            summaries[position] = targets
            continue
        if not targets:
            summaries[position] = skipped(job)
            continue
        cloud = _guarded(job, lambda: read_source(job, settings, blob))
        if isinstance(cloud, dict):
            summaries[position] = cloud
        else:
            ready.append((position, targets, cloud, start))
    if ready:
        results = _guarded_many(jobs, ready, settings)
        for (position, targets, cloud, start), result in zip(ready, results):
            job = jobs[position]
            if isinstance(result, dict):
                summaries[position] = result
                continue
            summaries[position] = _guarded(job, lambda: _written(job, settings, targets, cloud, result, start))
    return summaries


def warm_model(settings: Settings) -> None:
    """Create this process's onnxruntime session now (it is cached); a broken model is then each file's error."""
    from escape_cli.inference import load_model

    try:
        load_model(settings.model, settings.threads)
    except EscapeError:
        pass


def complete_file(job: CompletionJob, settings: Settings, data: bytes | None = None) -> dict:
    """Read, complete and write one file; returns its summary (raises EscapeError).

    The outputs are checked before the input is read: an existing output stops the
    job at once unless `settings.overwrite`; with `settings.skip_existing` a readable one
    is kept and, when every output of the job is there, the job is skipped.
    """
    from escape_cli.pipeline import complete

    start = time.perf_counter()
    targets = outputs_to_write(job, settings)
    if not targets:
        return skipped(job)
    cloud = read_source(job, settings, data)
    with errors_about(source_name(job)):
        result = complete(
            cloud, settings.model, normalize=settings.normalize, output_points=settings.points,
            keep_input=settings.keep_input, snap_radius=settings.snap_radius, solver=settings.solver,
            threads=settings.threads, anchor_sets=settings.anchor_sets,
        )
    return _written(job, settings, targets, cloud, result, start)


def _written(job: CompletionJob, settings: Settings, targets, cloud, result, start: float) -> dict:
    """Write a job's results; returns its summary."""
    write_results(job, settings, targets, result)
    return {
        "input": job.source, "output": job.output, "input_points": int(len(cloud)), **result.summary(),
        "seconds": round(time.perf_counter() - start, 3),
    }


def outputs_to_write(job: CompletionJob, settings: Settings) -> tuple[str, ...]:
    """The outputs of `job` to (re)write; empty when it is finished (`skip_existing`).

    Raises
    ------
    OutputExistsError
        An output exists and neither `overwrite` nor a readable file with `skip_existing`
        lets the job go on.
    InputFileError
        Unknown output format, or residuals asked for an npy output.
    """
    from escape_cli.io import is_stdio, output_format
    from escape_cli.io.files import is_stream

    out_fmt = output_format(job.output, settings.fmt)
    if settings.residuals and out_fmt in FIELDLESS_FORMATS:
        raise InputFileError(residuals_refusal(out_fmt))
    todo = []
    for target, fmt in ((job.output, out_fmt), (job.anchors, None)):
        if target is None:
            continue
        if fmt is None:
            fmt = output_format(target)
        if is_stdio(target) or is_stream(target) or not Path(target).exists():  # nothing to replace
            todo.append(target)
            continue
        if settings.skip_existing:
            problem = unreadable_output(target, fmt)
            if problem is None:
                continue  # finished before: keep it as it is
            if not settings.overwrite:
                raise OutputExistsError(f"{target} exists but is not a readable cloud ({problem}); use --overwrite to replace it")
        elif not settings.overwrite:
            raise OutputExistsError(f"{target} exists (use --overwrite to replace it)")
        todo.append(target)
    return tuple(todo)


def unreadable_output(path: str, fmt: str) -> str | None:
    """None when `path` reads back as a cloud in format `fmt`, else what is wrong with it."""
    from escape_cli.io import read_points

    try:
        read_points(path, fmt)
    except EscapeError as err:
        return str(err).removeprefix(f"{path}: ")
    return None


def read_source(job: CompletionJob, settings: Settings, data: bytes | None = None):
    """The (N, 3) float64 points of a job's input, from its file or from `data` (its bytes)."""
    from escape_cli.io import input_format, parse_point_fields, read_points

    if data is None:
        return read_points(job.source, settings.input_format)
    return parse_point_fields(data, source_name(job), input_format(job.source, settings.input_format))[0]


def write_results(job: CompletionJob, settings: Settings, targets, result) -> None:
    """Write a job's completed cloud and anchors, those of them named in `targets`."""
    from escape_cli.io import write_points

    if job.output in targets:
        fields = {"residual": result.residuals, "observed": result.is_observed.astype("float32")} if settings.residuals else None
        write_points(job.output, result.points, settings.fmt, overwrite=settings.overwrite, fields=fields, like=job.source)
    if job.anchors and job.anchors in targets:
        write_points(job.anchors, result.anchors, overwrite=settings.overwrite)


def source_name(job: CompletionJob) -> str:
    """The input's name in messages: its path as given, or <stdin>."""
    from escape_cli.io import display_name

    return display_name(job.source)


def skipped(job: CompletionJob) -> dict:
    """The summary of a job whose outputs were all there and readable."""
    return {"input": job.source, "output": job.output, "skipped": True}


def failure(job: CompletionJob, message: str) -> dict:
    """The summary of a job that failed."""
    return {"input": job.source, "error": message}


def _guarded(job: CompletionJob, work):
    """`work()`, or the job's failure summary when it raises: a bug for one file must not stop the others."""
    try:
        return work()
    except EscapeError as err:
        return failure(job, str(err))
    except Exception as err:
        return failure(job, f"internal error: {type(err).__name__}: {err}")


def _guarded_many(jobs, ready, settings: Settings) -> list:
    """The Completion of each ready scan, or its job's failure summary."""
    from escape_cli.pipeline import complete_many

    try:
        results = complete_many(
            [cloud for _, _, cloud, _ in ready], settings.model, batch_size=max(1, len(ready)),
            return_exceptions=True, normalize=settings.normalize, output_points=settings.points,
            keep_input=settings.keep_input, snap_radius=settings.snap_radius, solver=settings.solver,
            threads=settings.threads, anchor_sets=settings.anchor_sets,
        )
    except EscapeError as err:  # the model or an option: every scan of the chunk fails alike
        results = [err] * len(ready)
    except Exception as err:
        return [failure(jobs[position], f"internal error: {type(err).__name__}: {err}") for position, *_ in ready]
    named = [(jobs[position], result) for (position, *_), result in zip(ready, results)]
    return [failure(job, str(about(source_name(job), result))) if isinstance(result, EscapeError) else result
            for job, result in named]
