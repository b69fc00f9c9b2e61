"""`escape average-checkpoints`: one checkpoint whose weights are the mean of several from a run."""

from __future__ import annotations

from pathlib import Path
from typing import List

import typer

from escape_cli.cli.options import OVERWRITE, print_summary


def command(
    checkpoints: List[Path] = typer.Argument(..., help="Checkpoints of one run, e.g. OUT/snapshots/step*.pt."),
    output: Path = typer.Option(..., "--output", "-o", help="Checkpoint to write (.pt), for `escape export-onnx`."),
    validate: bool = typer.Option(True, "--validate/--no-validate", help="Score the average on the run's val split."),
    overwrite: bool = OVERWRITE,
) -> None:
    """Average the weights of checkpoints (the same network); keeps the latest one's metadata. Needs the train extra."""
    from escape_cli.cli.options import check_output
    from escape_cli.errors import InputFileError
    from escape_cli.extras import require

    require("torch", "escape average-checkpoints")

    for path in checkpoints:
        if not path.is_file():
            what = "is a folder, not a checkpoint file" if path.is_dir() else "does not exist"
            raise InputFileError(f"checkpoint {path} {what}")
    check_output(output, overwrite, inputs=checkpoints, make_parents=True)  # before any checkpoint is loaded

    from escape_cli.nn.average import average_checkpoints

    state = average_checkpoints(checkpoints, output, overwrite=overwrite, validate=validate)
    steps = [entry["step"] for entry in state["averaged_from"]]
    line = f"wrote {output}: the mean of {len(steps)} checkpoints (steps {min(steps)}-{max(steps)})"
    metrics = state.get("metrics")
    if metrics:
        line += f"; val CD-L1 x1000 {metrics['val_xyz_cd_l1_x1000']:.3f}"
    print_summary(line)
