"""`escape train`: train the network on a PCN-layout dataset (synthetic or the real PCN)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from escape_cli.cli.options import number_check, print_summary


def command(
    data: List[Path] = typer.Option(
        ..., "--data",
        help="PCN-layout dataset root (from `escape dataset synth`, or PCN); repeat to train on several (validation: the first's val split).",
    ),
    out: Path = typer.Option(..., "--out", help="Run folder: checkpoints, curve.csv, cache."),
    config: str = typer.Option("small", "--config", help="Network preset: small, paper (or tiny for tests)."),
    epochs: int = typer.Option(10, "--epochs", min=1),
    batch: int = typer.Option(8, "--batch", min=1),
    lr: float = typer.Option(5e-4, "--lr", callback=number_check(above=0.0)),
    seed: int = typer.Option(0, "--seed", min=0, max=2**63 - 1),
    device: str = typer.Option("cpu", "--device", help="cpu or cuda."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/last.pt."),
    val_every: int = typer.Option(0, "--val-every", min=0, help="Validate every N steps (0: each epoch)."),
    val_limit: int = typer.Option(400, "--val-limit", min=1, help="Validation samples used."),
    denoise: float = typer.Option(0.0, "--denoise", callback=number_check(minimum=0.0), help="Jitter input points by this sigma (denoising term)."),
    categories: Optional[List[str]] = typer.Option(None, "--categories", help="Category names or synsets."),
    views: Optional[int] = typer.Option(None, "--views", min=1, help="Use the first V partial views of each training object (default: all)."),
    workers: int = typer.Option(2, "--workers", min=1, help="Processes for preparing the data."),
    threads: int = typer.Option(0, "--threads", min=0, max=4096, help="Torch threads (0: default)."),
    xyz_weight: float = typer.Option(0.0, "--xyz-weight", callback=number_check(minimum=0.0), help="Add Chamfer-L1 in xyz after reconstruction, with this weight."),
    recall_weight: float = typer.Option(1.0, "--recall-weight", callback=number_check(above=0.0), help="Weight of the xyz term's truth-to-prediction half against its prediction-to-truth half (1: symmetric)."),
    init: Optional[Path] = typer.Option(None, "--init", help="Start from the weights of this checkpoint or exported .onnx model (new optimizer and schedule)."),
    max_steps: Optional[int] = typer.Option(None, "--max-steps", min=1, help="End the run (and its learning-rate schedule) after this many steps."),
    snapshot_every: int = typer.Option(0, "--snapshot-every", min=0, help="Keep the weights every N steps in OUT/snapshots (for `escape average-checkpoints`)."),
) -> None:
    """Train the distance-space completion network; keeps last.pt, best.pt and curve.csv in OUT.

    Needs the train extra (torch). The progress bar is on stderr (none with -q).
    """
    import logging

    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    from escape_cli.extras import require

    require("torch", "escape train")
    if init is not None and init.suffix.lower() == ".onnx":
        require("onnx", "escape train --init MODEL.onnx")
    from escape_cli.nn.config import get_preset
    from escape_cli.nn.train import Trainer, TrainOptions

    try:
        get_preset(config)  # fail early on an unknown preset
    except ValueError as err:
        raise typer.BadParameter(str(err), param_hint="--config") from None
    _check_device(device)
    if not resume and (out / "last.pt").exists():
        raise typer.BadParameter(f"{out} already holds a run; use --resume or another --out", param_hint="--out")
    _check_run_folder(out, data, init)
    options = TrainOptions(
        data=str(data[0]), extra_data=tuple(str(d) for d in data[1:]), out=str(out), config=config, epochs=epochs, batch=batch, lr=lr, seed=seed,
        device=device, val_every=val_every, val_limit=val_limit, denoise_sigma=denoise,
        categories=tuple(categories) if categories else None, views_per_object=views, workers=workers, threads=threads,
        max_steps=max_steps, xyz_weight=xyz_weight, recall_weight=recall_weight, snapshot_every=snapshot_every, init=str(init) if init else None,
    )
    trainer = Trainer(options, resume=resume)
    columns = [
        TextColumn("[bold]train"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
        TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn(),
    ]
    quiet = not logging.getLogger("escape").isEnabledFor(logging.WARNING)
    with Progress(*columns, transient=False, console=Console(stderr=True), disable=quiet) as progress:
        task = progress.add_task("train", total=None, info="")

        def report(step: int, total: int, loss: float, metrics: dict) -> None:
            val = metrics.get("val_xyz_cd_l1_x1000")
            info = f"loss x1000 {1000 * loss:.2f}" + (f"  val CD-L1 x1000 {val:.2f}" if val is not None else "")
            progress.update(task, completed=step, total=total, info=info)

        metrics = trainer.run(report)
    print_summary(f"done: step {trainer.step}, best val CD-L1 x1000 {trainer.best:.3f}, run in {out}")
    if metrics:
        print_summary(" ".join(f"{k}={v:.3f}" for k, v in metrics.items()))


def _check_device(device: str) -> None:
    """A usage error, before any work, for a device torch does not know or this machine lacks."""
    import torch

    try:
        kind = torch.device(device).type
    except (RuntimeError, ValueError):
        raise typer.BadParameter(f"unknown device {device!r} (cpu, cuda, cuda:N)", param_hint="--device") from None
    if kind == "cuda" and not torch.cuda.is_available():
        raise typer.BadParameter(f"{device}: no CUDA device is available here", param_hint="--device")


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
