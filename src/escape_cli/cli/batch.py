"""Running `escape complete` over many files: the input list, shards, output names, engines, reports."""

from __future__ import annotations

import json
import logging
import os
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import escape_cli.interrupts as interrupts
from escape_cli.cli.inputs import expand_inputs
from escape_cli.engines.jobs import CompletionJob, complete_file
from escape_cli.errors import InputFileError, ParameterError

log = logging.getLogger("escape")

ENGINES = ("local", "ray")


@dataclass(frozen=True)
class Plan:
    """The jobs of one `escape complete` run.

    jobs : this run's jobs (this shard's, with `--shard`).
    batch : outputs go to a folder, one JSON line per input, failures do not stop the
        others; else one input completed to one named file, in this process.
    total : inputs before sharding.
    """

    jobs: list[CompletionJob]
    batch: bool
    total: int


def plan_jobs(
    inputs, output: str, *, fmt=None, anchors_out=None, recursive: bool = False, files_from: str | None = None,
    shard: tuple[int, int] | None = None,
) -> Plan:
    """Map inputs to outputs: a file for one input, `<folder>/<stem>.<fmt>` for several.

    `files_from` names a list of input paths (one a line, '-' for stdin) added to
    `inputs`; with it or with `shard` the output is always a folder. `shard` (I, N)
    keeps every N-th input of the sorted list from the I-th on. Output folders are
    created and checked for writing here, before anything is read.
    """
    from escape_cli.io import check_writable_folder, is_stdio

    files = expand_inputs(list(inputs), recursive=recursive) if inputs else []
    if files_from is not None:
        files += read_files_from(files_from)
    if not files:
        raise InputFileError(f"{files_from or 'the input list'} names no files")
    listed = files_from is not None or shard is not None
    if not listed and len(files) == 1 and not output.endswith("/") and not Path(output).is_dir():
        if not is_stdio(output):
            check_writable_folder(Path(output).parent)
        if anchors_out:
            check_writable_folder(Path(anchors_out).parent)
        return Plan([CompletionJob(files[0], output, str(anchors_out) if anchors_out else None)], batch=False, total=1)
    if is_stdio(output):
        raise InputFileError("several inputs need an output folder, not '-'")
    if "-" in files:
        raise InputFileError("stdin ('-') can only be completed on its own")
    if shard is not None:
        files = sorted(dict.fromkeys(files))
    jobs = _batch_jobs(files, Path(output), fmt, anchors_out)
    total = len(jobs)
    if shard is not None:
        jobs = jobs[shard[0] :: shard[1]]
    check_writable_folder(output, create=True)
    if anchors_out:
        check_writable_folder(anchors_out, create=True)
    return Plan(jobs, batch=True, total=total)


def _batch_jobs(files: list[str], out_dir: Path, fmt, anchors_out) -> list[CompletionJob]:
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


def read_files_from(source: str) -> list[str]:
    """The paths listed in a file (or stdin for '-'), one a line; blank lines are skipped.

    Each line is a path as it is: no glob or folder expansion.
    """
    from escape_cli.io import display_name, read_input_bytes

    try:
        text = read_input_bytes(source).decode("utf-8", errors="surrogateescape")
    except InputFileError as err:
        raise InputFileError(f"--files-from: {err}") from None
    if "\0" in text:
        raise InputFileError(f"--files-from {display_name(source)}: not a text list of paths (it holds NUL bytes)")
    return [line.rstrip("\r") for line in text.split("\n") if line.strip()]


def parse_shard(text: str | None) -> tuple[int, int] | None:
    """'I/N' -> (I, N) with 0 <= I < N; None stays None."""
    if text is None:
        return None
    index, _, count = text.partition("/")
    try:
        i, n = int(index), int(count)
    except ValueError:
        i, n = -1, 0
    if n < 1 or not 0 <= i < n:
        raise ParameterError(f"--shard: must be I/N with 0 <= I < N (e.g. 0/4 ... 3/4), not {text!r}")
    return i, n


def check_model(model: str | None, threads: int, wait: bool = True) -> None:
    """Load the model (cached) so that a missing, misplaced or broken one is reported before any work.

    The metadata is always checked here; with `wait` False the session (checksum
    included) is left building: one scan is prepared meanwhile, and a corrupt model or
    a file onnxruntime refuses is reported before anything is written.
    """
    from escape_cli.inference import load_model

    net = load_model(model, threads)
    if wait:
        net.session  # noqa: B018 (waits for the session; raises ModelError if it failed)


def run_jobs(plan: Plan, settings: CompletionJob.Settings, *, workers: int, engine: str = "local",
             ray_address: str | None = None, summary_stream=sys.stderr) -> tuple[int, int]:
    """Complete every job, reporting one JSON line each; returns (failed, skipped) counts.

    A single file's error is raised as is (one line from the CLI); in a batch, failures
    are reported and the rest go on.
    """
    if not plan.batch:
        summary = complete_file(plan.jobs[0], settings)
        _report(summary, summary_stream)
        return 0, int(bool(summary.get("skipped")))
    if not plan.jobs:
        log.info("no inputs in this shard (%d in all)", plan.total)
        return 0, 0
    if engine == "ray":
        from escape_cli.engines.ray_engine import run_ray

        summaries = run_ray(plan.jobs, replace(settings, threads=1), actors=workers, address=ray_address)
    else:
        from escape_cli.engines.local import run_local

        threads = max(1, (os.cpu_count() or 1) // workers)
        summaries = run_local(plan.jobs, replace(settings, threads=threads), workers=workers)
    failed = skipped = 0
    with _progress(len(plan.jobs)) as advance:
        for summary in summaries:
            if "error" in summary:
                failed += 1
                print(f"escape: error: {error_line(summary)}", file=sys.stderr)
            elif summary.get("skipped"):
                skipped += 1
            _report(summary, summary_stream)
            advance()
    if skipped:
        log.info("%d of %d file(s) were done before and skipped", skipped, len(plan.jobs))
    return failed, skipped


def error_line(summary: dict) -> str:
    """A failed file's message, naming its input once (most messages start with it already)."""
    name, message = summary["input"], summary["error"]
    if name == "-":
        name = "<stdin>"
    return message if message.startswith((f"{name}:", f"{name} ")) else f"{name}: {message}"


def _report(summary: dict, stream) -> None:
    if stream is sys.stderr and not log.isEnabledFor(logging.WARNING):
        return  # -q
    print(json.dumps(summary), file=stream, flush=True)


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
            self.stop_on_interrupt = interrupts.on_interrupt(self.bar.stop)  # the terminal's cursor back
            self.stop_on_interrupt.__enter__()
            task = self.bar.add_task("completing", total=self.total)
            return lambda: self.bar.advance(task)
        return lambda: None

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.stop()
            self.stop_on_interrupt.__exit__(*exc)


__all__ = ["ENGINES", "CompletionJob", "Plan", "check_model", "parse_shard", "plan_jobs", "read_files_from", "run_jobs"]
