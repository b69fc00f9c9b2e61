"""`escape complete`: complete partial scans with the shipped (or a given) model."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import List, Optional

import typer

from escape_cli.cli.options import ANCHOR_SETS, FORMAT, INPUT_FORMAT, MODEL, NORMALIZE_HELP, OVERWRITE, SNAP_RADIUS

DEFAULT_POINTS = 16384


def command(
    inputs: Optional[List[str]] = typer.Argument(None, help="Partial clouds: files, folders, globs, or '-' for stdin."),
    output: str = typer.Option(..., "--output", "-o", help="Output file (one input), folder (several), or '-'."),
    model: Optional[str] = MODEL,
    normalize: str = typer.Option("auto", "--normalize", help=NORMALIZE_HELP),
    points: Optional[int] = typer.Option(
        None, "--points", "-n", min=1,
        help="Points in each completed cloud, at most what the model can produce (default 16384, or all a smaller model gives).",
    ),
    keep_input: bool = typer.Option(True, "--keep-input/--no-keep-input", help="Merge the observed points into the output."),
    snap_radius: Optional[float] = SNAP_RADIUS,
    anchor_sets: int = ANCHOR_SETS,
    anchors_out: Optional[Path] = typer.Option(None, "--anchors-out", help="Save the anchors: a file (one input) or a folder."),
    residuals: bool = typer.Option(False, "--residuals", help="Add per-point reconstruction residuals as a 'residual' field."),
    solver: str = typer.Option("batched", "--solver", help="batched (fast LM) or scipy (reference LM)."),
    workers: int = typer.Option(1, "--workers", "-w", min=1, help="Files completed in parallel (processes, or Ray actors)."),
    files_from: Optional[str] = typer.Option(None, "--files-from", help="Also complete the files listed in FILE, one path a line ('-': stdin)."),
    shard: Optional[str] = typer.Option(None, "--shard", help="I/N: complete only shard I (0 to N-1) of the sorted inputs."),
    skip_existing: bool = typer.Option(False, "--skip-existing", help="Skip inputs whose outputs exist and read back (resume a batch)."),
    engine: str = typer.Option("local", "--engine", help="local (worker processes) or ray (Ray Data; needs escape-cli\\[ray])."),
    ray_address: Optional[str] = typer.Option(None, "--ray-address", help="Ray cluster to join (e.g. auto); default: start Ray here."),
    fmt: Optional[str] = FORMAT,
    input_format: Optional[str] = INPUT_FORMAT,
    recursive: bool = typer.Option(False, "--recursive", "-r", help="Look for clouds in sub-folders too."),
    json_out: bool = typer.Option(False, "--json", help="Per-file JSON summaries on stdout (else on stderr)."),
    overwrite: bool = OVERWRITE,
) -> None:
    """Complete partial point clouds; the output stays in each input's frame and units."""
    from concurrent.futures import wait

    from escape_cli.inference import preload_model

    # One scan (the cold-start case): build the network's session while numpy and scipy
    # are imported and the scan is read and prepared.
    inputs = inputs or []
    single = len(inputs) == 1 and files_from is None and (inputs[0] == "-" or Path(inputs[0]).is_file())
    loading = preload_model(model) if single else None
    try:
        _complete(inputs, output, model, normalize, points, keep_input, snap_radius, anchor_sets, anchors_out, residuals, solver,
                  workers, files_from, shard, skip_existing, engine, ray_address, fmt, input_format, recursive,
                  json_out, overwrite, preloading=loading is not None)
    finally:
        if loading is not None:
            wait([loading])  # never leave the loader running at exit


def _complete(inputs, output, model, normalize, points, keep_input, snap_radius, anchor_sets, anchors_out, residuals, solver,
              workers, files_from, shard, skip_existing, engine, ray_address, fmt, input_format, recursive,
              json_out, overwrite, preloading: bool = False) -> None:
    from escape_cli.cli.batch import ENGINES, CompletionJob, check_model, parse_shard, plan_jobs, run_jobs
    from escape_cli.errors import EscapeError

    if normalize not in ("auto", "none"):
        raise typer.BadParameter("must be auto or none", param_hint="--normalize")
    if solver not in ("batched", "scipy"):
        raise typer.BadParameter("must be batched or scipy", param_hint="--solver")
    if engine not in ENGINES:
        raise typer.BadParameter(f"must be {' or '.join(ENGINES)}", param_hint="--engine")
    if ray_address is not None and engine != "ray":
        raise typer.BadParameter("needs --engine ray", param_hint="--ray-address")
    if not inputs and files_from is None:
        raise typer.BadParameter("give input files, folders or globs, or --files-from FILE", param_hint="INPUTS")
    shard_of = parse_shard(shard)
    points = _checked_model_options(model, points, anchor_sets)
    check_model(model, threads=0, wait=not preloading)
    plan = plan_jobs(inputs, output, fmt=fmt, anchors_out=anchors_out, recursive=recursive, files_from=files_from, shard=shard_of)
    _check_job_outputs(plan.jobs, fmt)
    settings = CompletionJob.Settings(
        model=model, normalize=normalize, points=points, keep_input=keep_input,
        snap_radius=snap_radius, anchor_sets=anchor_sets, residuals=residuals, solver=solver, fmt=fmt, overwrite=overwrite,
        input_format=input_format, skip_existing=skip_existing,
    )
    summary_stream = sys.stdout if json_out and output != "-" else sys.stderr
    failures, _ = run_jobs(plan, settings, workers=workers, engine=engine, ray_address=ray_address, summary_stream=summary_stream)
    if failures:
        raise EscapeError(f"{failures} of {len(plan.jobs)} file(s) failed")


def _checked_model_options(model: Optional[str], points: Optional[int], anchor_sets: int) -> int:
    """Before any file is read: the model (a path or a packaged name) and its metadata, --anchor-sets
    within its anchors, and --points (returned) within what it can produce."""
    from escape_cli.cli.options import check_anchor_sets
    from escape_cli.inference import check_output_points, max_output_points, model_path, read_metadata

    path = model_path(model)
    meta = read_metadata(path)
    check_anchor_sets(anchor_sets, meta["k"])
    if points is None:
        return min(DEFAULT_POINTS, max_output_points(meta))
    return check_output_points(points, meta, Path(path).name, name="--points")


def _check_job_outputs(jobs, fmt: Optional[str]) -> None:
    """Before any file is read: the output formats, and no output (completion or anchors) of
    any job is one of the inputs, --overwrite or not."""
    from escape_cli.io import output_format
    from escape_cli.io.files import check_distinct_outputs, check_not_input

    sources = [job.source for job in jobs]
    for job in jobs:
        output_format(job.output, fmt)
        if job.anchors is not None:
            output_format(job.anchors)
        check_not_input(job.output, sources)
        check_not_input(job.anchors, sources)
        check_distinct_outputs({"--output": job.output, "--anchors-out": job.anchors})
