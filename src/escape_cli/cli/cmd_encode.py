"""`escape encode`: a cloud's rotation-invariant encoding, its (N, K) distances to K anchors."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

import typer

from escape_cli.cli.options import (
    ANCHOR_K,
    ANCHOR_KNN,
    ANCHOR_METHOD,
    ANCHOR_RADIUS,
    INPUT_FORMAT,
    OVERWRITE,
    check_output,
    print_summary,
)
from escape_cli.errors import errors_about


def default_anchors_path(output: str) -> str:
    """Where the anchors go by default: ``d.npy`` -> ``d.anchors.ply`` (beside the distances)."""
    path = Path(output)
    if path.suffix.lower() == ".npy":
        return str(path.with_suffix(".anchors.ply"))
    return str(path.with_name(path.name + ".anchors.ply"))


def command(
    input_path: str = typer.Argument(..., metavar="IN", help="Point cloud ('-' for stdin)."),
    output: str = typer.Option(
        ..., "--output", "-o", help="Distance matrix to write, (N, K) float64 .npy ('-' for stdout)."
    ),
    anchors_out: Optional[str] = typer.Option(
        None, "--anchors-out", help="Anchor cloud to write (default: OUT with .anchors.ply; required with -o -)."
    ),
    k: int = ANCHOR_K,
    method: Literal["ball", "fps", "cluster"] = ANCHOR_METHOD,
    radius: float = ANCHOR_RADIUS,
    knn: int = ANCHOR_KNN,
    input_format: Optional[str] = INPUT_FORMAT,
    overwrite: bool = OVERWRITE,
) -> None:
    """Encode every point as its distances to K anchors; save the anchors to decode later.

    Row i of the matrix holds point i's distances to the anchors, in the order of the
    anchor cloud (written with float64 coordinates, so decoding is exact).
    """
    import numpy as np

    from escape_cli.core.anchors import select_anchors
    from escape_cli.core.encoding import distance_matrix
    from escape_cli.errors import OutputFileError
    from escape_cli.io import display_name, output_format, read_points, write_array, write_points
    from escape_cli.io.files import check_distinct_outputs

    if output == "-" and anchors_out is None:
        raise OutputFileError("-o - writes the distances to stdout; give --anchors-out FILE for the anchors")
    if output != "-" and Path(output).suffix.lower() != ".npy":
        raise OutputFileError(f"the distances are written as .npy; name the output *.npy (got {output})")
    anchors_path = anchors_out if anchors_out is not None else default_anchors_path(output)
    if anchors_path == "-" and output == "-":
        raise OutputFileError("distances and anchors cannot both go to stdout")
    output_format(anchors_path)  # an unknown format fails now, not after the work
    check_distinct_outputs({"--output": output, "--anchors-out": anchors_path})
    check_output(output, overwrite, inputs=[input_path])
    check_output(anchors_path, overwrite, inputs=[input_path])

    points = read_points(input_path, input_format)  # (N, 3)
    with errors_about(display_name(input_path)):
        anchors = select_anchors(points, k=k, method=method, radius=radius, knn=knn)
        distances = distance_matrix(points, anchors.points)  # (N, K) float64

    # Anchors first: in `encode -o - | decode - --anchors A`, decode reads A once stdin ends.
    write_points(anchors_path, anchors.points, overwrite=overwrite, coordinate_dtype=np.float64)
    write_array(output, distances, overwrite=overwrite)
    print_summary(
        f"encoded {len(points)} points with {len(anchors.indices)} anchors ({method}) -> "
        f"{output} ({distances.shape[0]} x {distances.shape[1]} float64), anchors -> {anchors_path}"
    )
