"""Entry point of the `escape` command: the Typer app, global options, error handling.

Each subcommand lives in its own module `cmd_<name>.py`; heavy libraries are imported
inside the command bodies so that `escape --help` stays fast. `python -m escape_cli` runs
the same `main()`; `escape --install-completion` installs shell completion (bash, zsh,
fish, PowerShell).
"""

from __future__ import annotations

import logging
import sys
from typing import Optional

import typer

from escape_cli.version import __version__
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
    add_completion=True,
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


GLOBAL_OPTIONS = ("-q", "--quiet", "-v", "-vv", "-vvv", "--verbose", "--version")
PROG_NAME = "escape"  # also under `python -m escape_cli`: usage lines, and the completion variable _ESCAPE_COMPLETE


def usage_error_line(err: typer.TyperException) -> str:
    """One line for a command-line usage error: the option concerned, then what is wrong with it.

    `err` is one of the usage errors of the click that typer carries (UsageError and its
    subclasses BadParameter, MissingParameter, NoSuchOption...), told apart by their
    attributes so that no private module is imported.
    """
    kind = type(err).__name__
    option = getattr(err, "option_name", None)
    if kind == "NoSuchOption" and option in GLOBAL_OPTIONS:
        return f"{option} is a global option: put it before the command (escape {option} COMMAND ...)"
    param = getattr(err, "param", None)
    hint = getattr(err, "param_hint", None) or (param.opts[0] if getattr(param, "opts", None) else getattr(param, "name", None))
    if isinstance(hint, (list, tuple)):
        hint = hint[0]
    if kind == "MissingParameter" and hint:
        return f"{hint}: missing (required)"
    if kind == "BadParameter" and hint:
        return f"{str(hint).strip(chr(39))}: {' '.join(str(err.message).split())}"
    return " ".join(err.format_message().split())


def main() -> None:
    """Run the CLI; turn usage errors and escape's own errors into one line and an exit code."""
    try:
        code = app(standalone_mode=False, prog_name=PROG_NAME)
    except typer.Abort:
        print("escape: interrupted", file=sys.stderr)
        sys.exit(130)
    except typer.TyperException as err:  # click's errors as typer carries them
        if type(err).__name__ == "NoArgsIsHelpError":
            print(err.format_message(), file=sys.stderr)
            sys.exit(2)
        if getattr(err, "exit_code", 1) == 2:
            print(f"escape: error: {usage_error_line(err)} (see --help)", file=sys.stderr)
            sys.exit(2)
        print(f"escape: error: {' '.join(err.format_message().split())}", file=sys.stderr)
        sys.exit(getattr(err, "exit_code", 1))
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
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
