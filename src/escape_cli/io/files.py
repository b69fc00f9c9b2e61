"""Bytes in and out of files or stdin/stdout, with atomic, no-clobber writes.

Every reader in `escape_cli.io` reads the whole input into memory first (point clouds
of a few million points at most), so files and pipes are handled the same way.
"""

from __future__ import annotations

import errno
import os
import sys
from pathlib import Path

from escape_cli.errors import InputFileError, OutputExistsError, OutputFileError

STDIO = "-"


def is_stdio(path: str | Path) -> bool:
    """True when `path` is ``-`` (stdin for a reader, stdout for a writer)."""
    return str(path) == STDIO


def display_name(path: str | Path) -> str:
    """The name used in messages: the path as given, or ``<stdin>`` for ``-``."""
    return "<stdin>" if is_stdio(path) else str(path)


def read_input_bytes(path: str | Path) -> bytes:
    """All the bytes of a file, or of stdin when `path` is ``-``.

    Raises
    ------
    InputFileError
        Missing file, a directory, or a file that cannot be read.
    """
    if is_stdio(path):
        return sys.stdin.buffer.read()
    try:
        with open(path, "rb") as handle:
            return handle.read()
    except FileNotFoundError:
        raise InputFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputFileError(f"{path} is a directory, not a point-cloud file") from None
    except PermissionError:
        raise InputFileError(f"{path}: permission denied") from None
    except OSError as err:
        raise InputFileError(f"{path}: cannot read ({err.strerror or err})") from None


def write_output_bytes(path: str | Path, data: bytes, *, overwrite: bool = False) -> None:
    """Write `data` to a file atomically, or to stdout when `path` is ``-``.

    The bytes go to a temporary file in the target's directory, which then takes the
    target's name in one step: readers never see a half-written file, and a failed
    write leaves no trace. Without `overwrite` an existing target is never replaced,
    even if it appears while writing.

    Raises
    ------
    OutputExistsError
        The target exists and `overwrite` is false.
    OutputFileError
        The target's directory is missing or not writable, or the target is a directory.
    """
    if is_stdio(path):
        sys.stdout.buffer.write(data)
        sys.stdout.buffer.flush()
        return
    target = Path(path)
    if target.is_dir():
        raise OutputFileError(f"{target} is a directory; give a file name")
    if target.exists() and not overwrite:
        raise OutputExistsError(f"{target} exists (use --overwrite to replace it)")
    directory = target.parent
    if not directory.is_dir():
        raise OutputFileError(f"cannot write {target}: directory {directory} does not exist")
    temp = _create_temp_file(target)
    try:
        _write_all(temp, data, target)
        if overwrite:
            os.replace(temp, target)
        else:
            _link_without_clobbering(temp, target)
    finally:
        if temp.exists():
            temp.unlink()


def _create_temp_file(target: Path) -> Path:
    """Create an empty, exclusive temporary file beside `target` (umask applies)."""
    for attempt in range(100):
        temp = target.with_name(f".{target.name}.{os.getpid()}.{attempt}.tmp")
        try:
            fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        except PermissionError:
            raise OutputFileError(f"cannot write {target}: permission denied") from None
        except OSError as err:
            raise OutputFileError(f"cannot write {target}: {err.strerror or err}") from None
        os.close(fd)
        return temp
    raise OutputFileError(f"cannot write {target}: no free temporary name beside it")


def _write_all(temp: Path, data: bytes, target: Path) -> None:
    try:
        with open(temp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
    except OSError as err:
        raise OutputFileError(f"cannot write {target}: {err.strerror or err}") from None


def _link_without_clobbering(temp: Path, target: Path) -> None:
    """Give `temp` the name `target`, failing if `target` exists (hard link, then unlink)."""
    try:
        os.link(temp, target)
    except FileExistsError:
        raise OutputExistsError(f"{target} exists (use --overwrite to replace it)") from None
    except OSError as err:
        if err.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK):
            raise OutputFileError(f"cannot write {target}: {err.strerror or err}") from None
        # The file system has no hard links: the existence check above has to do.
        if target.exists():
            raise OutputExistsError(f"{target} exists (use --overwrite to replace it)") from None
        os.replace(temp, target)
