"""`escape encode` (being written)."""

import typer


def command() -> None:
    """Not available yet."""
    raise typer.Exit(3)
