"""`escape train`: train the network on a PCN-layout dataset (synthetic or the real PCN)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from escape_cli.cli.options import number_check, print_summary


def command(
    context: typer.Context,
    data: Optional[List[Path]] = typer.Option(
        None, "--data",
        help="PCN-layout dataset root (from `escape dataset synth`, or PCN); repeat to train on several (validation: the first's val split). Required, except that --resume keeps the run's.",
    ),
    out: Path = typer.Option(..., "--out", help="Run folder: checkpoints, curve.csv (and the cache unless --cache)."),
    config: str = typer.Option("small", "--config", help="Network preset: small, small-deep (small with 6+6 transformer layers), small-refine (small with two coarse-to-fine offset steps after the fold); both grow from a small model by --init; paper (or tiny for tests)."),
    epochs: int = typer.Option(10, "--epochs", min=1),
    batch: int = typer.Option(8, "--batch", min=1),
    lr: float = typer.Option(5e-4, "--lr", callback=number_check(above=0.0)),
    seed: int = typer.Option(0, "--seed", min=0, max=2**63 - 1),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/last.pt, with the run's options: each one given again replaces the run's (--max-steps N stretches or shortens the schedule); --device, --threads and --workers are this machine's."),
    val_every: int = typer.Option(0, "--val-every", min=0, help="Validate every N steps (0: each epoch)."),
    val_limit: int = typer.Option(400, "--val-limit", min=1, help="Validation samples used."),
    val_xyz: int = typer.Option(24, "--val-xyz", min=1, help="Validation samples of each set also reconstructed and scored in xyz (the score that picks best.pt)."),
    denoise: float = typer.Option(0.0, "--denoise", callback=number_check(minimum=0.0), help="Jitter input points by this sigma (denoising term)."),
    augment_noise: float = typer.Option(0.0, "--augment-noise", callback=number_check(minimum=0.0), help="Jitter each training input by a sigma drawn from [0, this] (network-frame units; a partial's radius is about 0.28)."),
    augment_density: float = typer.Option(1.0, "--augment-density", callback=number_check(above=0.0, maximum=1.0), help="Each training input keeps a fraction of its points drawn from [this, 1] (a sparser scan; 1: off)."),
    categories: Optional[List[str]] = typer.Option(None, "--categories", help="Category names or synsets."),
    views: Optional[int] = typer.Option(None, "--views", min=1, help="Use the first V partial views of each training object (default: all)."),
    workers: int = typer.Option(2, "--workers", min=1, help="Processes for preparing the data."),
    threads: int = typer.Option(0, "--threads", min=0, max=4096, help="Torch threads (0: default)."),
    xyz_weight: float = typer.Option(0.0, "--xyz-weight", callback=number_check(minimum=0.0), help="Add Chamfer-L1 in xyz after reconstruction, with this weight."),
    recall_weight: float = typer.Option(1.0, "--recall-weight", callback=number_check(above=0.0), help="Weight of the xyz term's truth-to-prediction half against its prediction-to-truth half (1: symmetric)."),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from the weights of this checkpoint or exported .onnx model (new optimizer and schedule); --resume keeps the run's record of it."),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", min=1, help="End the run (and its learning-rate schedule) after this many steps."),
    snapshot_every: int = typer.Option(0, "--snapshot-every", min=0, help="Keep the weights every N steps in OUT/snapshots (for `escape average-checkpoints`)."),
    precision: str = typer.Option(
        "fp32", "--precision", metavar="fp32|bf16",
        help="fp32, or bf16: the forward under bfloat16 autocast, ~2x faster on CPUs with AVX512-BF16 (weights, optimizer and checkpoints stay float32). Default fp32; --resume keeps the run's.",
    ),
    cache: Optional[Path] = typer.Option(
        None, "--cache", help="Folder of the prepared-data caches, shareable by runs (default OUT/cache; --resume keeps the run's).",
    ),
    val_data: Optional[List[Path]] = typer.Option(
        None, "--val-data",
        help="Validate on this dataset's val split; repeat for several (scored by the mean of xyz CD-L1 / input-copy CD-L1). Default: the first --data's; --resume keeps the run's.",
    ),
) -> None:
    """Train the distance-space completion network; keeps last.pt, best.pt and curve.csv in OUT.

    Needs the train extra (torch). Progress is on stderr (none with -q): a bar on a
    terminal, else a line every 100 steps and one per validation (for a log file).
    """
    import logging

    from escape_cli.cli.train_progress import train_progress
    from escape_cli.extras import require

    require("torch", "escape train")
    if init is not None and init.suffix.lower() == ".onnx":
        require("onnx", "escape train --init MODEL.onnx")
    from escape_cli.errors import EscapeError
    from escape_cli.nn.config import get_preset
    from escape_cli.nn.train import PRECISIONS, Trainer, TrainOptions, saved_options

    try:
        get_preset(config)  # fail early on an unknown preset
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="--config") from None
    if precision not in PRECISIONS:
        raise typer.BadParameter(f"must be {' or '.join(PRECISIONS)}, got {precision!r}", param_hint="--precision")
    _check_device(device)
    if resume and init is not None:
        raise typer.BadParameter("--resume goes on from OUT/last.pt's weights; --init starts a new run (give it another --out)", param_hint="--init")
    if not resume and (out / "last.pt").exists():
        raise typer.BadParameter(f"{out} already holds a run; use --resume or another --out", param_hint="--out")
    saved = saved_options(out) if resume else {}
    if not data:
        if resume and not saved:
            raise EscapeError(f"cannot resume: {out / 'last.pt'} does not exist")
        data = _saved_data(saved)
        if not data:
            raise typer.BadParameter("missing (required; only --resume keeps the run's)", param_hint="--data")
    _check_run_folder(out, data, init)
    run = dict(
        config=config, epochs=epochs, batch=batch, lr=lr, seed=seed, val_every=val_every, val_limit=val_limit,
        xyz_val_samples=val_xyz, denoise_sigma=denoise, augment_noise=augment_noise, augment_density=augment_density,
        categories=tuple(categories) if categories else None, views_per_object=views, max_steps=max_steps,
        xyz_weight=xyz_weight, recall_weight=recall_weight, snapshot_every=snapshot_every, precision=precision,
        cache=str(cache) if cache else None, val_data=tuple(str(d) for d in val_data or ()),
    )
    if resume:
        run.update(_kept_run_options(context, saved, config))
        if saved.get("init"):
            init = Path(saved["init"])  # the record of where the run started; last.pt holds its weights
    _check_val_data(run["val_data"], Path(run["cache"]) if run["cache"] else None)
    options = TrainOptions(
        data=str(data[0]), extra_data=tuple(str(d) for d in data[1:]), out=str(out), device=device, workers=workers,
        threads=threads, init=str(init) if init else None, **run,
    )
    trainer = Trainer(options, resume=resume)
    several = len(trainer.val_sets) > 1
    quiet = not logging.getLogger("escape").isEnabledFor(logging.WARNING)
    with train_progress(trainer, quiet) as report:
        metrics = trainer.run(report)
    best = f"best val xyz/input CD-L1 (mean of {len(trainer.val_sets)} sets)" if several else "best val CD-L1 x1000"
    print_summary(f"done: step {trainer.step}, {best} {trainer.best:.3f}, run in {out}")
    if metrics:
        print_summary(" ".join(f"{k}={v:.3f}" for k, v in metrics.items()))


# What a run is (not the machine it runs on): the command-line name of each, and its TrainOptions field.
RUN_OPTIONS = {
    "config": "config", "epochs": "epochs", "batch": "batch", "lr": "lr", "seed": "seed", "val_every": "val_every",
    "val_limit": "val_limit", "val_xyz": "xyz_val_samples", "denoise": "denoise_sigma", "augment_noise": "augment_noise",
    "augment_density": "augment_density", "categories": "categories", "views": "views_per_object", "max_steps": "max_steps",
    "xyz_weight": "xyz_weight", "recall_weight": "recall_weight", "snapshot_every": "snapshot_every",
    "precision": "precision", "cache": "cache", "val_data": "val_data",
}


def _kept_run_options(context: typer.Context, saved: dict, config: str) -> dict:
    """The run's saved value of every RUN_OPTIONS option not given on this command line (a --resume goes on as it was).

    The network cannot change under a run: a --config other than the run's is a usage error.
    """
    from escape_cli.nn.train import TrainOptions

    run = TrainOptions.from_dict({"data": "", "out": "", **saved})  # the saved values in their types
    given = {name for name in RUN_OPTIONS if getattr(context.get_parameter_source(name), "name", None) == "COMMANDLINE"}
    if "config" in given and "config" in saved and run.config != config:
        raise typer.BadParameter(f"the run is a {run.config} network; a resumed run keeps it (leave --config out)", param_hint="--config")
    return {field: getattr(run, field) for name, field in RUN_OPTIONS.items() if name not in given and field in saved}


def _saved_data(saved: dict) -> List[Path]:
    """The datasets of a saved run (its first --data, then the others); [] without one."""
    if not saved.get("data"):
        return []
    return [Path(saved["data"]), *(Path(root) for root in saved.get("extra_data") or ())]


def _check_device(device: str) -> None:
    """A usage error, before any work, for a device torch does not know or this machine lacks."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise typer.BadParameter(f"unknown device {device!r} (cpu, cuda, cuda:N)", param_hint="--device") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter(f"{device}: no CUDA device is available here", param_hint="--device")


def _check_val_data(val_roots: tuple, cache: Optional[Path]) -> None:
    """Usage errors for --val-data folders that are missing or share a name; a --cache that cannot be written into."""
    from escape_cli.errors import EscapeError
    from escape_cli.nn.train import set_names

    for root in val_roots:
        if not (Path(root) / "val").is_dir():
            raise typer.BadParameter(f"{root} has no val split (a PCN-layout dataset with val/ expected)", param_hint="--val-data")
    try:
        set_names(val_roots)
    except EscapeError as err:
        raise typer.BadParameter(str(err), param_hint="--val-data") from None
    if cache is not None:
        from escape_cli.io.files import check_output_folder

        check_output_folder(cache)


def _check_run_folder(out: Path, data: List[Path], init: Optional[Path]) -> None:
    """The run folder is neither the dataset nor a file, can be written, and does not hold --init.

    A run writes OUT/last.pt, OUT/best.pt and OUT/snapshots/: starting from one of them
    would overwrite the weights it starts from.
    """
    from escape_cli.errors import OutputFileError
    from escape_cli.io.files import check_output_folder, same_file

    if any(same_file(out, root) for root in data):
        raise OutputFileError(f"--out {out} is the dataset folder --data; give the run its own folder")
    check_output_folder(out)
    if init is None:
        return
    written = [out / "last.pt", out / "best.pt"]
    snapshots = (out / "snapshots").resolve()
    if any(same_file(init, path) for path in written) or snapshots in Path(init).resolve().parents:
        raise OutputFileError(
            f"--init {init} is a checkpoint this run would overwrite; copy it elsewhere or train into another --out"
        )
