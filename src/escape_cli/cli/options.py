"""Options and small helpers shared by several commands."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from escape_cli.errors import OutputExistsError

OVERWRITE = typer.Option(False, "--overwrite", help="Replace output files that already exist.")
FORMAT = typer.Option(
    None, "--format", "-f", help="File format (ply, pcd, xyz, txt, pts, npy); default: from the extension."
)
JSON_OUT = typer.Option(False, "--json", help="Print machine-readable JSON on stdout.")


def check_output(path: Optional[Path | str], overwrite: bool) -> None:
    """Refuse to overwrite an existing output unless `overwrite` is set ('-' is stdout)."""
    if path is None or str(path) == "-":
        return
    if Path(path).exists() and not overwrite:
        raise OutputExistsError(f"{path} exists (use --overwrite to replace it)")
