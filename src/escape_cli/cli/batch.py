"""Running `escape complete` over many files: planning outputs, workers, per-file reports."""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from escape_cli.cli.inputs import expand_inputs
from escape_cli.errors import EscapeError, InputFileError

log = logging.getLogger("escape")


@dataclass(frozen=True)
class CompletionJob:
    """One input file and where its results go."""

    source: str
    output: str
    anchors: str | None = None

    @dataclass(frozen=True)
    class Settings:
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


def plan_jobs(inputs, output: str, *, fmt, anchors_out, recursive: bool, overwrite: bool) -> list[CompletionJob]:
    """Map inputs to outputs: a file for one input, `<folder>/<stem>.<fmt>` for several."""
    files = expand_inputs(list(inputs), recursive=recursive)
    single = len(files) == 1 and not output.endswith("/") and not Path(output).is_dir()
    if single:
        return [CompletionJob(files[0], output, str(anchors_out) if anchors_out else None)]
    if output == "-":
        raise InputFileError("several inputs need an output folder, not '-'")
    if "-" in files:
        raise InputFileError("stdin ('-') can only be completed on its own")
    out_dir = Path(output)
    out_dir.mkdir(parents=True, exist_ok=True)
    if anchors_out:
        Path(anchors_out).mkdir(parents=True, exist_ok=True)
    suffix = "." + (fmt or "ply")
    jobs, seen = [], {}
    for src in files:
        stem = Path(src).stem
        target = out_dir / f"{stem}{suffix}"
        if target in seen:
            raise InputFileError(f"{src} and {seen[target]} would both be written to {target}; complete them separately")
        seen[target] = src
        anchors = str(Path(anchors_out) / f"{stem}.anchors.ply") if anchors_out else None
        jobs.append(CompletionJob(src, str(target), anchors))
    return jobs


def complete_file(job: CompletionJob, settings: CompletionJob.Settings) -> dict:
    """Read, complete and write one file; returns its JSON summary (raises EscapeError)."""
    from escape_cli.cli.options import check_output, errors_about
    from escape_cli.io import display_name, output_format, read_points, write_points
    from escape_cli.pipeline import complete

    start = time.perf_counter()
    check_output(job.output, settings.overwrite)
    check_output(job.anchors, settings.overwrite)
    out_fmt = output_format(job.output, settings.fmt)
    if settings.residuals and out_fmt == "npy":
        raise InputFileError("--residuals needs a ply, pcd, xyz or npz output (npy holds coordinates only)")
    cloud = read_points(job.source, settings.input_format)
    with errors_about(display_name(job.source) if job.source != "-" else "<stdin>"):
        result = complete(
            cloud, settings.model, normalize=settings.normalize, output_points=settings.points,
            keep_input=settings.keep_input, snap_radius=settings.snap_radius, solver=settings.solver, threads=settings.threads,
        )
    fields = {"residual": result.residuals, "observed": result.is_observed.astype("float32")} if settings.residuals else None
    write_points(job.output, result.points, out_fmt, overwrite=settings.overwrite, fields=fields, like=job.source)
    if job.anchors:
        write_points(job.anchors, result.anchors, overwrite=settings.overwrite)
    return {
        "input": job.source, "output": job.output, "input_points": int(len(cloud)), **result.summary(),
        "seconds": round(time.perf_counter() - start, 3),
    }


def _safe_complete(args) -> dict:
    job, settings = args
    try:
        return complete_file(job, settings)
    except EscapeError as err:
        return {"input": job.source, "error": str(err)}
    except Exception as err:  # a bug for this file must not stop the others
        return {"input": job.source, "error": f"internal error: {type(err).__name__}: {err}"}


def run_jobs(jobs: list[CompletionJob], settings, *, workers: int, summary_stream=sys.stderr) -> int:
    """Complete every job, reporting one JSON line each; returns the number that failed.

    A single job's error is raised as is (one line from the CLI); in a batch, failures
    are reported and the rest go on.
    """
    if len(jobs) == 1:
        summary = complete_file(jobs[0], settings)
        _report(summary, summary_stream)
        return 0
    import os

    threads = max(1, (os.cpu_count() or 1) // workers)
    settings = CompletionJob.Settings(**{**asdict(settings), "threads": threads})
    failures = 0
    with _progress(len(jobs)) as advance:
        for summary in _map(_safe_complete, [(job, settings) for job in jobs], workers):
            if "error" in summary:
                failures += 1
                print(f"escape: error: {summary['input']}: {summary['error']}", file=sys.stderr)
            _report(summary, summary_stream)
            advance()
    return failures


def _report(summary: dict, stream) -> None:
    if stream is sys.stderr and not log.isEnabledFor(logging.WARNING):
        return  # -q
    print(json.dumps(summary), file=stream, flush=True)


def _map(func, items, workers: int):
    if workers <= 1:
        for item in items:
            yield func(item)
        return
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(workers) as pool:
        yield from pool.imap(func, items)


class _progress:
    """A rich progress bar on stderr for batches, only when stderr is a terminal."""

    def __init__(self, total: int):
        self.total = total
        self.bar = None

    def __enter__(self):
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import Progress

            self.bar = Progress(console=Console(stderr=True), transient=True)
            self.bar.start()
            task = self.bar.add_task("completing", total=self.total)
            return lambda: self.bar.advance(task)
        return lambda: None

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.stop()
