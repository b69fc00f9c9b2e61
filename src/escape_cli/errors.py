"""The exceptions escape raises for a user's mistake or bad data.

The CLI turns every `EscapeError` into one line on stderr and a non-zero exit code;
anything else is a bug and is reported as such.
"""

from contextlib import contextmanager


class EscapeError(Exception):
    """Base class: a problem the user can fix (bad file, bad option, bad geometry)."""

    exit_code = 1


class ParameterError(EscapeError, ValueError):
    """An argument or option value is out of range or of the wrong kind (a usage error)."""

    exit_code = 2


class InputFileError(EscapeError):
    """A file is missing, unreadable, corrupt or in an unknown format."""


class FormatError(ParameterError, InputFileError):
    """A format name (``--format``, ``--input-format``) or file extension escape does not know: a usage error."""


class PointCloudError(EscapeError, ValueError):
    """A cloud cannot be used: empty, too small, non-finite, wrong shape."""


class DegenerateGeometryError(EscapeError):
    """Geometry too degenerate to work with (all points equal, collinear anchors...)."""


class OutputExistsError(EscapeError):
    """An output file exists and `--overwrite` was not given."""


class ModelError(EscapeError):
    """A model file is missing, corrupt, or does not match its metadata."""


class DatasetError(EscapeError):
    """A dataset folder does not have the expected layout."""


class OutputFileError(EscapeError):
    """An output cannot be written: missing directory, no permission, not a file."""


class MissingDependencyError(EscapeError):
    """An optional library (an extra of the package) that a command needs is not installed."""


@contextmanager
def errors_about(name: str):
    """Prefix the escape errors raised inside the block with `name` (the file concerned).

    A core function's "has 5 points; at least 8 needed" becomes
    "scan.ply: has 5 points; at least 8 needed"; a message that already starts with
    the name is left as it is.
    """
    try:
        yield
    except EscapeError as err:
        named = about(name, err)
        if named is err:
            raise
        raise named from None


def about(name: str, err: EscapeError) -> EscapeError:
    """`err` with its message prefixed by `name` (the same error when it already starts with it)."""
    if str(err).startswith(f"{name}:"):
        return err
    return type(err)(f"{name}: {err}")


def one_line(text: str) -> str:
    """`text` as one printable line: newlines, escape sequences and other control characters escaped."""
    out = []
    for char in str(text):
        if char.isprintable():
            out.append(char)
        elif char in "\n\r\t":
            out.append({"\n": "\\n", "\r": "\\r", "\t": "\\t"}[char])
        else:
            code = ord(char)
            out.append(f"\\x{code:02x}" if code < 0x100 else f"\\u{code:04x}")
    return "".join(out)
