"""Entry point of the `escape` command: the Typer app, global options, error handling.

Each subcommand lives in its own module `cmd_<name>.py`; heavy libraries are imported
inside the command bodies so that `escape --help` stays fast. `python -m escape_cli` runs
the same `main()`; `escape --install-completion` installs shell completion (bash, zsh,
fish, PowerShell).

`main` keeps the CLI's promises: every user error, usage error and environment failure
is one line `escape: error: ...` on stderr (control characters escaped) with a non-zero
exit code, never a traceback: 2 for usage, 1 for data and for a full disk or memory,
130 for Ctrl-C (`escape: interrupted`), 141 for a closed stdout pipe (quietly, as a Unix
tool killed by SIGPIPE), 70 for a bug (`internal error`; `-vv` shows the traceback).
Python warnings (numpy's, onnxruntime's) become debug log lines, shown with `-vv`.
"""

from __future__ import annotations

import errno
import functools
import logging
import os
import sys
import warnings
from typing import Callable, Optional

import typer

from escape_cli.version import __version__
from escape_cli.cli.argv import GLOBAL_OPTIONS
from escape_cli.cli.streams import is_closed_stdout_error
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
from escape_cli.errors import EscapeError, one_line

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



def _guarded(command: Callable) -> Callable:
    """Run a command inside `escape_cli.io.files.guard_inputs`: no write may replace a file it read."""

    @functools.wraps(command)
    def run(*args, **kwargs):
        from escape_cli.io.files import guard_inputs  # numpy comes with escape_cli.io: not for --help

        with guard_inputs():
            return command(*args, **kwargs)

    return run


app.command("anchors")(_guarded(cmd_anchors.command))
app.command("encode")(_guarded(cmd_encode.command))
app.command("decode")(_guarded(cmd_decode.command))
app.command("complete")(_guarded(cmd_complete.command))
app.command("eval")(_guarded(cmd_eval.command))
app.command("export-onnx")(_guarded(cmd_export_onnx.command))
app.command("train")(_guarded(cmd_train.command))
app.command("average-checkpoints")(_guarded(cmd_average_checkpoints.command))
app.command("render")(_guarded(cmd_render.command))
app.add_typer(cmd_dataset.app, name="dataset")


# Errors of the machine rather than of escape or its input: one line, exit code 1.
ENVIRONMENT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS}

EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE: what a shell reports for a tool killed by a closed pipe
EXIT_INTERNAL = 70  # EX_SOFTWARE


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
        return f"{str(hint).strip(chr(39))}: {bad_value_message(err)}"
    return " ".join(err.format_message().split())


def bad_value_message(err: typer.TyperException) -> str:
    """What is wrong with an option's value, in the wording of `escape_cli.core.params`.

    typer validates values with pydantic and carries its error as the cause; its
    structured record (type, limit, input) gives "must be at least 1, got 0" rather than
    "Input should be greater than or equal to 1".
    """
    message = " ".join(str(err.message).split())
    try:
        record = err.__cause__.errors()[0]  # a pydantic ValidationError, duck-typed
        kind, limits, given = record["type"], record.get("ctx") or {}, record.get("input")
    except (AttributeError, IndexError, KeyError, TypeError):
        return _click_value_message(message, getattr(getattr(err, "param", None), "type", None))
    got = "" if given is None else f", got {_shown(given)}"
    for key, wording in (("ge", "at least"), ("gt", "greater than"), ("le", "at most"), ("lt", "less than")):
        if key in limits and kind.startswith(("greater_than", "less_than")):
            return f"must be {wording} {limits[key]:g}{got}"
    if kind.startswith("int_"):
        return f"must be an integer{got}"
    if kind.startswith("float_"):
        return f"must be a number{got}"
    if kind == "value_error":
        return message.removeprefix("Value error, ").rstrip(".")
    return message


def _click_value_message(message: str, param_type) -> str:
    """click's own range and type messages ("0 is not in the range x>=1.", "'abc' is not a
    valid integer.", typer before 0.29) in the wording of `escape_cli.core.params`."""
    import re

    match = re.match(r"^(?P<value>.+?) is not a valid (?P<kind>integer|int|float)\b", message)
    if match:
        wanted = "a number" if match["kind"] == "float" else "an integer"
        return f"must be {wanted}, got {_shown(match['value'].strip(chr(39)))}"
    match = re.match(r"^(?P<value>.+?) is not in the range ", message)
    if not match:
        return message.rstrip(".")
    given = match["value"].strip(chr(39))
    low, high = getattr(param_type, "min", None), getattr(param_type, "max", None)
    low_open, high_open = getattr(param_type, "min_open", False), getattr(param_type, "max_open", False)
    try:
        value = float(given)
    except ValueError:
        return message.rstrip(".")
    if low is not None and (value < low or (value == low and low_open)):
        return f"must be {'greater than' if low_open else 'at least'} {low:g}, got {given}"
    if high is not None:
        return f"must be {'less than' if high_open else 'at most'} {high:g}, got {given}"
    return message.rstrip(".")


def _shown(value) -> str:
    """A value as the user typed it: numbers bare, anything else quoted."""
    try:
        float(value)
        return str(value)
    except (TypeError, ValueError):
        return repr(value)




def main() -> None:
    """Run the CLI; turn every error into one line and an exit code (see the module docstring)."""
    sys.exit(run(sys.argv[1:]))


def run(argv: list[str]) -> int:
    """Run ``escape ARGV...``; returns the exit code, having printed any error as one line."""
    with warnings.catch_warnings():
        warnings.showwarning = _warning_to_log
        stdout_before = _stdout_identity()
        try:
            code = _invoke(argv)
            if sys.stdout is not None:
                sys.stdout.flush()  # a full disk or a closed pipe under stdout shows here, not at exit
            return code
        except SystemExit as exit_:
            # rich (help pages, tables) answers a broken pipe by pointing stdout at
            # /dev/null and exiting with 1: the same event as our BrokenPipeError
            devnull = _devnull_identity()
            if exit_.code == 1 and stdout_before not in (None, devnull) and _stdout_identity() == devnull:
                return EXIT_BROKEN_PIPE
            raise
        except BrokenPipeError:
            _detach_stdout()
            return EXIT_BROKEN_PIPE
        except KeyboardInterrupt:
            return _fail("interrupted", EXIT_INTERRUPTED, prefix="escape: ")
        except typer.Abort:
            return _fail("interrupted", EXIT_INTERRUPTED, prefix="escape: ")
        except typer.TyperException as err:  # click's errors as typer carries them
            if type(err).__name__ == "NoArgsIsHelpError":
                print(err.format_message(), file=sys.stderr)
                return 2
            if getattr(err, "exit_code", 1) == 2:
                return _usage_fail(usage_error_line(err))
            return _fail(" ".join(err.format_message().split()), getattr(err, "exit_code", 1))
        except EscapeError as err:
            if err.exit_code == 2:  # a usage error, like click's
                return _usage_fail(str(err))
            return _fail(str(err), err.exit_code)
        except MemoryError:
            return _fail("out of memory (a smaller cloud, or fewer --points, may fit)", 1)
        except OSError as err:
            if is_closed_stdout_error(err):  # `escape --version >&-`: as GNU tools say it
                _detach_stdout()
                return _fail(f"cannot write to stdout: {err.strerror or err}", 1)
            if err.errno not in ENVIRONMENT_ERRNOS or log.isEnabledFor(logging.DEBUG):
                return _internal_error(err)
            where = f" {err.filename}" if err.filename else " to stdout"  # files' errors name them
            _detach_stdout()
            return _fail(f"cannot write{where}: {err.strerror or err}", 1)
        except Exception as err:  # a bug: keep it one line unless -vv asked for the traceback
            return _internal_error(err)


PROG_NAME = "escape"  # also under `python -m escape_cli`: usage lines, and the completion variable _ESCAPE_COMPLETE


def _invoke(argv: list[str]) -> int:
    """Parse and run the command (typer's own runner would swallow Ctrl-C and broken pipes)."""
    if os.environ.get(f"_{PROG_NAME.upper()}_COMPLETE"):  # the shell asks for completions: typer answers and exits
        return app(args=list(argv), prog_name=PROG_NAME)
    command = typer.main.get_command(app)
    try:
        with command.make_context(PROG_NAME, list(argv)) as ctx:
            result = command.invoke(ctx)
    except typer.Exit as exit_:  # --help, --version
        return exit_.exit_code
    return result if isinstance(result, int) else 0


def _usage_fail(message: str) -> int:
    """A usage error: its one line points at --help; exit code 2."""
    return _fail(f"{message.rstrip('.')} (see --help)", 2)


def _fail(message: str, code: int, prefix: str = "escape: error: ") -> int:
    try:
        print(prefix + one_line(message), file=sys.stderr, flush=True)
    except OSError:  # stderr itself is gone: the exit code still says it
        pass
    return code


def _internal_error(err: Exception) -> int:
    if log.isEnabledFor(logging.DEBUG):
        raise err
    message = f"internal error: {type(err).__name__}: {err} (run with -vv for the traceback)"
    return _fail(message, EXIT_INTERNAL, prefix="escape: ")


def _warning_to_log(message, category, filename, lineno, file=None, line=None) -> None:
    """`warnings.showwarning` for the CLI: a debug line instead of two raw lines on stderr."""
    log.debug("%s: %s (%s:%d)", category.__name__, message, filename, lineno)


def _stdout_identity() -> tuple[int, int] | None:
    """(device, inode) of what stdout's file descriptor points at; None for an in-memory stream."""
    try:
        stat = os.fstat(sys.stdout.fileno())
    except (AttributeError, OSError, ValueError):
        return None
    return stat.st_dev, stat.st_ino


def _devnull_identity() -> tuple[int, int]:
    stat = os.stat(os.devnull)
    return stat.st_dev, stat.st_ino


def _detach_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's last flush cannot fail again."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # an in-memory stream: nothing to detach
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


if __name__ == "__main__":
    main()
