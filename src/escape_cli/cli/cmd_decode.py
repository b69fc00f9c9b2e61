"""`escape decode`: recover points from their distances to the anchors (Levenberg-Marquardt)."""

from __future__ import annotations

from typing import Literal, Optional

import typer

from escape_cli.cli.options import ASCII, FORMAT, OVERWRITE, check_output, print_summary
from escape_cli.errors import errors_about


def command(
    distances_path: str = typer.Argument(..., metavar="DIST", help="(M, K) distance matrix .npy ('-' for stdin)."),
    anchors_path: str = typer.Option(..., "--anchors", "-a", help="The K anchors the distances refer to."),
    output: str = typer.Option(..., "--output", "-o", help="Point cloud to write ('-' for stdout, binary PLY)."),
    solver: Literal["batched", "scipy"] = typer.Option(
        "batched", "--solver", help="batched: vectorised LM (fast); scipy: per-point least_squares (reference)."
    ),
    residuals: bool = typer.Option(
        False, "--residuals", help="Add each point's RMS distance residual as a scalar field 'residual'."
    ),
    fmt: Optional[str] = FORMAT,
    ascii_body: bool = ASCII,
    overwrite: bool = OVERWRITE,
) -> None:
    """Reconstruct coordinates from distances to anchors, e.g. those written by `escape encode`.

    Prints one summary line on stderr (points, mean/max residual, anchor spread)
    unless -q.
    """
    import numpy as np

    from escape_cli.errors import InputFileError, OutputFileError, PointCloudError
    from escape_cli.formats import FIELDLESS_FORMATS, residuals_refusal
    from escape_cli.io import display_name, output_format, read_array, read_points, write_points
    from escape_cli.core.checks import as_rows
    from escape_cli.core.reconstruction import reconstruct

    if distances_path == "-" and anchors_path == "-":
        raise InputFileError("distances and anchors cannot both come from stdin")
    out_format = output_format(output, fmt)  # an unknown format fails now, not after the work
    if residuals and out_format in FIELDLESS_FORMATS:
        raise OutputFileError(residuals_refusal(out_format))
    check_output(output, overwrite, inputs=[distances_path, anchors_path])

    # Distances before anchors: in `encode -o - | decode - --anchors A`, A is complete
    # once stdin has ended.
    distances_name = display_name(distances_path)
    distances = as_rows(read_array(distances_path), f"{distances_name}: distances", columns=None, min_rows=1, letters="MK")  # (M, K)
    anchors = read_points(anchors_path)  # (K, 3)
    if distances.shape[1] != len(anchors):
        raise PointCloudError(
            f"{distances_name} has {distances.shape[1]} distances per point but {anchors_path} holds "
            f"{len(anchors)} anchors; decode with the anchors the distances were encoded with"
        )
    _check_not_negative(distances, distances_name)
    with errors_about(str(anchors_path)), np.errstate(all="ignore"):
        result = reconstruct(distances, anchors, method=solver)
    _check_decoded(result.points, distances, anchors, distances_name, str(anchors_path))

    fields = {"residual": result.residuals} if residuals else None
    write_points(output, result.points, fmt, overwrite=overwrite, fields=fields, binary=not ascii_body)
    spread = "near-planar (two-sided starts used)" if result.near_planar else "well spread"
    print_summary(
        f"decoded {len(result.points)} points from {len(anchors)} anchors ({solver}): residual mean "
        f"{result.residuals.mean():.3g}, max {result.residuals.max():.3g}; anchors {spread} -> {output}"
    )


def _check_not_negative(distances, name: str) -> None:
    """Distances are never negative: a negative one is a damaged or foreign file, not noise to solve."""
    from escape_cli.errors import PointCloudError

    negative = distances < 0  # (M, K)
    if negative.any():
        count, rows = int(negative.sum()), int(negative.any(axis=1).sum())
        raise PointCloudError(
            f"{name}: {count} negative distance{'s' if count > 1 else ''} in {rows} of {len(distances)} rows "
            f"(smallest {float(distances.min()):.3g}); distances to anchors are never negative"
        )


def _check_decoded(points, distances, anchors, name: str, anchors_name: str) -> None:
    """Refuse coordinates that are not finite or too large to use: the distances do not fit the anchors."""
    import numpy as np

    from escape_cli.core.checks import MAX_MAGNITUDE
    from escape_cli.errors import PointCloudError

    with np.errstate(all="ignore"):
        largest = float(np.max(np.abs(points))) if points.size else 0.0
    if not np.isfinite(largest) or largest > MAX_MAGNITUDE:
        spread = float(np.max(np.abs(anchors - anchors.mean(axis=0))))
        got = "non-finite coordinates" if not np.isfinite(largest) else f"coordinates up to {largest:.3g}"
        raise PointCloudError(
            f"{name}: the distances (up to {float(distances.max()):.3g}) do not fit the anchors of {anchors_name} "
            f"(within {spread:.3g} of their centre): decoding gives {got}"
        )
