"""`escape anchors`: choose the K anchor points of a cloud and save them (or print JSON)."""

from __future__ import annotations

from typing import Literal, Optional

import typer

from escape_cli.cli.options import (
    ANCHOR_K,
    ANCHOR_KNN,
    ANCHOR_METHOD,
    ANCHOR_RADIUS,
    ASCII,
    FORMAT,
    INPUT_FORMAT,
    JSON,
    OVERWRITE,
    check_output,
    print_summary,
)
from escape_cli.errors import errors_about


def command(
    input_path: str = typer.Argument(..., metavar="IN", help="Point cloud ('-' for stdin)."),
    output: Optional[str] = typer.Option(
        None, "--output", "-o", help="Anchor cloud to write, K points ('-' for stdout); optional with --json."
    ),
    k: int = ANCHOR_K,
    method: Literal["ball", "fps", "cluster"] = ANCHOR_METHOD,
    radius: float = ANCHOR_RADIUS,
    knn: int = ANCHOR_KNN,
    fmt: Optional[str] = FORMAT,
    input_format: Optional[str] = INPUT_FORMAT,
    ascii_body: bool = ASCII,
    overwrite: bool = OVERWRITE,
    json_out: bool = JSON,
) -> None:
    """Choose the anchors of a cloud (deterministic FPS, refined towards high curvature).

    The anchor cloud is written with float64 coordinates so that it is exact.
    """
    import json

    import numpy as np

    from escape_cli.core.anchors import select_anchors
    from escape_cli.errors import OutputFileError
    from escape_cli.io import display_name, output_format, read_points, write_points

    if output is None and not json_out:
        raise OutputFileError("no output: give -o OUT for the anchor cloud, or --json")
    if output == "-" and json_out:
        raise OutputFileError("-o - and --json both write to stdout; give -o a file name")
    if output is not None or fmt is not None:
        output_format(output or "-", fmt)  # an unknown format fails now, not after the work
    check_output(output, overwrite, inputs=[input_path])

    points = read_points(input_path, input_format)  # (N, 3)
    with errors_about(display_name(input_path)):
        anchors = select_anchors(points, k=k, method=method, radius=radius, knn=knn)

    if output is not None:
        write_points(
            output, anchors.points, fmt, overwrite=overwrite, binary=not ascii_body, coordinate_dtype=np.float64
        )
    if json_out:
        report = {
            "input": input_path,
            "points": len(points),
            "output": output,
            "method": method,
            "k": k,
            "radius": radius,
            "knn": knn,
            "indices": anchors.indices.tolist(),
            "anchors": anchors.points.tolist(),
        }
        print(json.dumps(report))
    else:
        print_summary(f"{len(anchors.indices)} anchors ({method}) chosen on {len(points)} points -> {output}")
