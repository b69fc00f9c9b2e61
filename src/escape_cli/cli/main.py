"""Entry point of the `escape` command: the Typer app, global options, error handling.

Each subcommand lives in its own module `cmd_<name>.py`; heavy libraries are imported
inside the command bodies so that `escape --help` stays fast.
"""

from __future__ import annotations

import logging
import sys
from typing import Optional

import typer

from escape_cli import __version__
from escape_cli.cli import (
    cmd_anchors,
    cmd_average_checkpoints,
    cmd_complete,
    cmd_dataset,
    cmd_decode,
    cmd_encode,
    cmd_eval,
    cmd_export_onnx,
    cmd_render,
    cmd_train,
)
from escape_cli.errors import EscapeError

app = typer.Typer(
    name="escape",
    help="Rotation-equivariant completion of partial point clouds (ESCAPE).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

log = logging.getLogger("escape")


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"escape {__version__}")
        raise typer.Exit()


@app.callback()
def _global_options(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help="More log output on stderr (-vv for debug)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only errors on stderr."),
    version: Optional[bool] = typer.Option(
        None, "--version", callback=_version_callback, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Rotation-equivariant completion of partial point clouds (ESCAPE)."""
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    logging.basicConfig(level=level, format="escape: %(levelname)s: %(message)s", stream=sys.stderr, force=True)


app.command("anchors")(cmd_anchors.command)
app.command("encode")(cmd_encode.command)
app.command("decode")(cmd_decode.command)
app.command("complete")(cmd_complete.command)
app.command("eval")(cmd_eval.command)
app.command("export-onnx")(cmd_export_onnx.command)
app.command("train")(cmd_train.command)
app.command("average-checkpoints")(cmd_average_checkpoints.command)
app.command("render")(cmd_render.command)
app.add_typer(cmd_dataset.app, name="dataset")


def main() -> None:
    """Run the CLI; turn escape's own errors into one line and an exit code."""
    try:
        app(standalone_mode=True)
    except EscapeError as err:
        print(f"escape: error: {err}", file=sys.stderr)
        sys.exit(err.exit_code)
    except KeyboardInterrupt:
        print("escape: interrupted", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:
        sys.exit(141)
    except Exception as err:  # a bug: keep it one line unless -vv asked for the traceback
        if log.isEnabledFor(logging.DEBUG):
            raise
        print(f"escape: internal error: {type(err).__name__}: {err} (run with -vv for the traceback)", file=sys.stderr)
        sys.exit(70)


if __name__ == "__main__":
    main()
