"""Options and small helpers shared by several commands."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, Optional

import typer

import escape_cli.packaged_models as packaged_models
from escape_cli.core.settings import DEFAULTS as ANCHOR_DEFAULTS
from escape_cli.formats import FORMAT_LIST


def number_check(*, minimum: float | None = None, above: float | None = None, maximum: float | None = None) -> Callable:
    """A typer callback that refuses a float option's value unless it is finite and within bounds.

    typer (pydantic) accepts ``nan``, ``inf`` and ``1e400`` for a float; this makes them the
    same one-line usage error as any other bad value, with `escape_cli.core.params`' wording:
    ``--snap-radius: must be a finite number, got inf``.
    """
    from escape_cli.core.params import as_number
    from escape_cli.errors import ParameterError

    def callback(value: Optional[float]) -> Optional[float]:
        if value is None:
            return value
        try:
            return as_number(value, "the value", minimum=minimum, above=above, maximum=maximum)
        except ParameterError as err:
            raise typer.BadParameter(str(err).removeprefix("the value ")) from None

    return callback


OVERWRITE = typer.Option(False, "--overwrite", help="Replace output files that already exist (never an input).")
FORMAT = typer.Option(
    None, "--format", "-f", help=f"Output file format ({FORMAT_LIST}); default: from the extension."
)
JSON = typer.Option(False, "--json", help="Print machine-readable JSON lines on stdout.")
MODEL = typer.Option(
    None, "--model", "-m", metavar="NAME|PATH",
    help=(f"A packaged model ({packaged_models.listing()}) or an exported .onnx file; "
          f"default: ${packaged_models.MODEL_ENV}, else {packaged_models.DEFAULT}."),
)
"""`--model` of the commands that run the network: the packaged names listed from their folder (no model is read)."""
NORMALIZE_HELP = (
    "auto: each scan is completed in its own frame (centre and size from the scan; any units, mapped back exactly); "
    "none: feed coordinates as they are (only for older models trained in absolute PCN units)."
)
ANCHOR_SETS = typer.Option(
    1, "--anchor-sets", min=1,
    help="Complete from this many anchor sets (at most the model's anchors, 8) and pool the points: more of the unseen parts, S times the time.",
)


def check_anchor_sets(anchor_sets: int, k: int) -> None:
    """A usage error for --anchor-sets above the model's K anchors."""
    if anchor_sets > k:
        raise typer.BadParameter(f"must be at most {k}, the model's anchors", param_hint="--anchor-sets")


SNAP_RADIUS = typer.Option(
    None, "--snap-radius", callback=number_check(minimum=0.0),
    help="Pull predicted points within about this distance of the scan onto its surface, in model units (default 0.08; 0: off).",
)


def check_output(path: Optional[Path | str], overwrite: bool, inputs: Iterable = (), make_parents: bool = False) -> None:
    """Check an output file before any work ('-' is stdout): see `escape_cli.io.files.check_output_path`.

    Never one of `inputs`, whatever `overwrite` says; an existing file only with
    `overwrite`; a directory that exists and is writable (or, with `make_parents`, can be
    made).
    """
    from escape_cli.io.files import check_output_path

    check_output_path(path, overwrite=overwrite, inputs=inputs, make_parents=make_parents)


# --- anchors, input format, ascii bodies, summaries (anchors / encode / decode) ---

ANCHOR_K = typer.Option(ANCHOR_DEFAULTS.k, "--k", "-k", min=4, help="Number of anchors (at least 4).")
ANCHOR_METHOD = typer.Option(
    ANCHOR_DEFAULTS.method, "--method", help="Anchor choice: ball (FPS refined to high curvature), fps, or cluster."
)
ANCHOR_RADIUS = typer.Option(
    ANCHOR_DEFAULTS.radius, "--radius", callback=number_check(above=0.0),
    help="Search radius of the ball refinement, in the cloud's units.",
)
ANCHOR_KNN = typer.Option(ANCHOR_DEFAULTS.knn, "--knn", min=3, help="Neighbours for the curvature estimate.")
INPUT_FORMAT = typer.Option(
    None, "--input-format", help=f"Input file format ({FORMAT_LIST}); default: from the extension (sniffed for stdin)."
)
ASCII = typer.Option(False, "--ascii", help="Write PLY/PCD with a text body instead of binary.")


def print_summary(line: str) -> None:
    """Print one human-readable line on stderr, unless -q was given."""
    import logging
    import sys

    if logging.getLogger("escape").isEnabledFor(logging.WARNING):
        print(line, file=sys.stderr)
