"""`escape export-onnx`: a training checkpoint to an ONNX model plus its metadata JSON."""

from __future__ import annotations

from pathlib import Path

import typer

from escape_cli.cli.options import OVERWRITE, print_summary


def command(
    checkpoint: Path = typer.Argument(..., help="Checkpoint from `escape train` (best.pt or last.pt)."),
    output: Path = typer.Option(..., "--output", "-o", help="Model file to write (.onnx); NAME.json goes beside it."),
    opset: int = typer.Option(17, "--opset", help="ONNX opset version."),
    overwrite: bool = OVERWRITE,
) -> None:
    """Export to ONNX (dynamic batch axis) and check onnxruntime against torch (<= 1e-4); needs the train extra."""
    from escape_cli.cli.options import check_output
    from escape_cli.errors import InputFileError
    from escape_cli.extras import require
    from escape_cli.io.files import check_distinct_outputs

    require("torch", "escape export-onnx")
    require("onnx", "escape export-onnx")

    if output.suffix.lower() != ".onnx":
        raise InputFileError(f"the model file must end in .onnx, got {output}")
    if not checkpoint.is_file():
        what = "is a folder, not a checkpoint file" if checkpoint.is_dir() else "does not exist"
        raise InputFileError(f"checkpoint {checkpoint} {what}")
    meta_path = output.with_suffix(".json")
    check_distinct_outputs({"the model": output, "its metadata": meta_path})
    for path in (output, meta_path):  # before torch is even imported
        check_output(path, overwrite, inputs=[checkpoint], make_parents=True)

    from escape_cli.nn.export import export_onnx

    meta = export_onnx(checkpoint, output, overwrite=overwrite, opset=opset)
    size = output.stat().st_size / 1e6
    print_summary(
        f"wrote {output} ({size:.1f} MB, {meta['parameters']} parameters) and {output.with_suffix('.json')}; "
        f"onnxruntime vs torch max |diff| {meta['onnx_parity_max_abs']:.1e}"
    )
