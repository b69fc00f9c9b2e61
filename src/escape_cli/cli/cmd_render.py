"""`escape render`: draw point clouds side by side to a PNG (orthographic, depth-shaded)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from escape_cli.cli.options import INPUT_FORMAT, OVERWRITE, check_output, print_summary

VALUE_FILE_SUFFIXES = (".npy", ".txt", ".csv")


def command(
    inputs: List[str] = typer.Argument(..., metavar="IN...", help="Point clouds to draw, one column each."),
    output: Path = typer.Option(..., "--output", "-o", help="PNG file to write."),
    color_by: Optional[List[str]] = typer.Option(
        None, "--color-by",
        help="Per-point values to colour by: a .npy/.txt file or a field name of the input (e.g. curvature). "
        "Give it once for every input or once per input.",
    ),
    views: int = typer.Option(3, "--views", min=1, max=4, help="Views per cloud: front, side, top, oblique (first N)."),
    size: int = typer.Option(256, "--size", min=16, max=4096, help="Side of each view's panel in pixels."),
    input_format: Optional[str] = INPUT_FORMAT,
    overwrite: bool = OVERWRITE,
) -> None:
    """Draw clouds side by side (columns) in fixed orthographic views (rows), y up."""
    from escape_cli.errors import FormatError, InputFileError
    from escape_cli.io import read_point_fields
    from escape_cli.io.files import write_output_bytes
    from escape_cli.render_png import encode_png, render_clouds

    if output.suffix.lower() != ".png":  # an unknown output format: a usage error, as for the other commands
        raise FormatError(f"unknown image format '{output.suffix or '(no extension)'}' for {output}; render writes .png")
    check_output(output, overwrite, inputs=[*inputs, *(color_by or [])])
    if color_by and len(color_by) not in (1, len(inputs)):
        raise InputFileError(f"--color-by given {len(color_by)} times for {len(inputs)} inputs; give it once or once per input")
    clouds, values = [], []
    for i, path in enumerate(inputs):
        points, fields = read_point_fields(path, input_format)  # (N, 3), {name: (N,)}
        clouds.append(points)
        source = None if not color_by else color_by[0 if len(color_by) == 1 else i]
        values.append(None if source is None else _values_for(source, points, fields, path))
    image = render_clouds(clouds, values, n_views=views, size=size)
    write_output_bytes(output, encode_png(image), overwrite=overwrite)  # atomic, never over an input
    print_summary(f"escape: drew {len(clouds)} cloud(s) x {views} view(s) to {output}")


def _values_for(source: str, points, fields: dict, input_path: str):
    """Per-point values from a values file or from a field of the input cloud; returns (N,) float64."""
    import numpy as np

    from escape_cli.errors import InputFileError

    if Path(source).suffix.lower() in VALUE_FILE_SUFFIXES or Path(source).is_file():
        if Path(source).suffix.lower() == ".npy":
            from escape_cli.io import read_array

            values = read_array(source)
        else:
            try:
                values = np.loadtxt(source, dtype=np.float64, ndmin=1)
            except (OSError, ValueError) as err:
                raise InputFileError(f"{source}: cannot read values ({err})") from None
        values = np.asarray(values, dtype=np.float64)
        if values.ndim == 2 and values.shape[1] == 1:
            values = values[:, 0]
        if values.ndim != 1:
            raise InputFileError(f"{source}: values must be one number per point, got shape {values.shape}")
    elif source in fields:
        values = np.asarray(fields[source], dtype=np.float64)
    else:
        known = ", ".join(sorted(fields)) or "none"
        raise InputFileError(f"{input_path}: no field {source!r} to colour by (fields: {known}), and no such file")
    if len(values) != len(points):
        raise InputFileError(f"{source}: {len(values)} values for {len(points)} points of {input_path}")
    return values
