"""`escape dataset` (being written)."""

import typer

app = typer.Typer(help="Make and inspect training datasets.", no_args_is_help=True)
