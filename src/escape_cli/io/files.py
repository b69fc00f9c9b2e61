"""Bytes in and out of files or stdin/stdout, with atomic, no-clobber writes that never touch an input.

Every reader in `escape_cli.io` reads the whole input into memory first (point clouds
of a few million points at most), so files and pipes are handled the same way.

The rules for an output, in one place (`check_output_path`, called by every command
before any work, and again by `write_output_bytes`): it is never one of the inputs (the
same path, a symlink to it or a hard link: the same file, whatever ``--overwrite``
says), never a directory, replaces an existing file only with ``overwrite``, and its
directory must exist and be writable. A symlink is written through: its target gets
the new bytes, the link stays. An existing character device or FIFO (``/dev/null``,
``/dev/stdout``, a named pipe) is a stream: the bytes are written into it, in order, and
it is never replaced by a file, so it needs no ``--overwrite``; a block device or socket
is refused. Within `guard_inputs()` (the CLI runs every
command inside it) every file read is remembered, and a write that would replace one
of them is refused too.
"""

from __future__ import annotations

import errno
import os
import re
import stat
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, Optional

import escape_cli.interrupts as interrupts
from escape_cli.errors import InputFileError, OutputExistsError, OutputFileError

STDIO = "-"
NEVER_OVER_INPUTS = "escape never writes over its inputs, with or without --overwrite; give another output file"

_inputs_read: Optional[set[tuple[int, int]]] = None
"""(device, inode) of every file read inside `guard_inputs()`; None outside it."""


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
        try:
            return sys.stdin.buffer.read()
        except OSError as err:  # closed (`<&-`), or a read error of the pipe or terminal
            raise InputFileError(f"<stdin>: cannot read ({err.strerror or err})") from None
    try:
        with open(path, "rb") as handle:
            if _inputs_read is not None:
                _inputs_read.add(_identity(os.fstat(handle.fileno())))
            return handle.read()
    except FileNotFoundError:
        raise InputFileError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise InputFileError(f"{path} is a directory, not a point-cloud file") from None
    except PermissionError:
        raise InputFileError(f"{path}: permission denied") from None
    except OSError as err:
        raise InputFileError(f"{path}: cannot read ({err.strerror or err})") from None


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when `a` and `b` name the same file: the same path once symlinks and ``..`` are
    resolved, or the same device and inode (a hard link). ``-`` is never a file."""
    if is_stdio(a) or is_stdio(b):
        return False
    try:
        if Path(a).resolve() == Path(b).resolve():
            return True
        return _identity(os.stat(a)) == _identity(os.stat(b))
    except (OSError, RuntimeError):  # missing (then no inode to share), or a symlink loop
        return False


def check_not_input(path: str | Path | None, inputs: Iterable) -> None:
    """Raise OutputFileError when the output `path` is one of `inputs` (see `same_file`).

    None and ``-`` pass; so do None and ``-`` among `inputs`.
    """
    if path is None or is_stdio(path):
        return
    for source in inputs:
        if source is not None and same_file(path, source):
            raise OutputFileError(f"{_input_clash(Path(path), source)}: {NEVER_OVER_INPUTS}")


def check_output_path(
    path: str | Path | None, *, overwrite: bool = False, inputs: Iterable = (), make_parents: bool = False
) -> None:
    """Refuse an output before any work is done (None and ``-``, stdout, always pass).

    Parameters
    ----------
    path : str or Path or None
        The output file.
    overwrite : bool
        Whether an existing file may be replaced (never an input).
    inputs : iterable of str or Path
        The command's input files (None and ``-`` are skipped).
    make_parents : bool
        The writer creates missing directories: check the nearest existing one instead.

    Raises
    ------
    OutputFileError
        `path` is one of `inputs` (the same path, a symlink to it, or a hard link), a
        directory, or its directory is missing, not a directory or not writable.
    OutputExistsError
        `path` exists and `overwrite` is false.
    """
    if path is None or is_stdio(path):
        return
    target = Path(path)
    check_not_input(target, inputs)
    if is_stream(target):
        return
    if target.is_dir():
        raise OutputFileError(f"{target} is a directory; give a file name")
    if target.exists() and not overwrite:
        raise OutputExistsError(f"{target} exists (use --overwrite to replace it)")
    directory = _nearest_existing(target.parent) if make_parents else target.parent
    check_output_directory(directory, target)


def check_output_folder(folder: str | Path, *, inputs: Iterable = ()) -> None:
    """Refuse an output folder (created when missing) before any work is done.

    Raises
    ------
    OutputFileError
        `folder` is a file, is or lies inside one of the `inputs` (folders whose files
        are read: what is written there could become an input), or it cannot be created
        or written into.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputFileError(f"cannot write into {folder}: it is a file, not a folder")
    resolved = folder.resolve()
    for source in inputs:
        if source is None or is_stdio(source):
            continue
        other = Path(source).resolve()
        if resolved == other or other in resolved.parents:
            never = NEVER_OVER_INPUTS.replace("file", "folder")
            raise OutputFileError(f"output folder {folder} is inside the input {source}: {never}")
    check_output_directory(_nearest_existing(folder), folder)


def check_output_directory(directory: str | Path, target: str | Path | None = None) -> None:
    """Raise OutputFileError unless `directory` exists, is a directory and is writable.

    `target` (what is to be written in it) only changes the message.
    """
    directory = Path(directory)
    what = f"cannot write {target}" if target is not None else f"cannot write into {directory}"
    if not directory.exists():
        raise OutputFileError(f"{what}: directory {directory} does not exist")
    if not directory.is_dir():
        raise OutputFileError(f"{what}: {directory} is not a directory")
    if not os.access(directory, os.W_OK | os.X_OK):
        if _read_only(directory):
            raise OutputFileError(f"{what}: {directory} is on a read-only file system")
        raise OutputFileError(f"{what}: permission denied (directory {directory})")


def check_distinct_outputs(outputs: dict[str, str | Path | None]) -> None:
    """Raise OutputFileError when two of a command's outputs ({option: path}) are the same file."""
    named = [(option, path) for option, path in outputs.items() if path is not None and not is_stdio(path)]
    for i, (option, path) in enumerate(named):
        for other_option, other in named[i + 1 :]:
            if same_file(path, other):
                raise OutputFileError(f"{option} and {other_option} name the same file {path}; give two different files")


@contextmanager
def guard_inputs() -> Iterator[None]:
    """Inside the block, remember every file read and refuse any write that would replace one.

    The CLI runs each command in it; library callers who read a file and mean to write
    over it stay free to.
    """
    global _inputs_read
    saved, _inputs_read = _inputs_read, set()
    try:
        yield
    finally:
        _inputs_read = saved


def write_output_bytes(path: str | Path, data: bytes, *, overwrite: bool = False) -> None:
    """Write `data` to a file atomically, or to stdout when `path` is ``-``.

    The bytes go to a temporary file in the target's directory, which then takes the
    target's name in one step: readers never see a half-written file, and a failed
    write leaves no trace. Without `overwrite` an existing target is never replaced,
    even if it appears while writing; a file read inside `guard_inputs()` never is.

    Raises
    ------
    OutputExistsError
        The target exists and `overwrite` is false.
    OutputFileError
        The target's directory is missing or not writable, the target is a directory or
        an input, or stdout cannot take the bytes (a full disk).
    BrokenPipeError
        stdout is a pipe whose reader has gone.
    """
    if is_stdio(path):
        _write_stdout(data)
        return
    check_output_path(path, overwrite=overwrite)
    if is_stream(path):
        _write_stream(Path(path), data)
        return
    target = _write_through_links(Path(path))
    _check_not_read(target)
    temp = _create_temp_file(target)
    try:
        _write_all(temp, data, target)
        if overwrite:
            _check_not_read(target)
            os.replace(temp, target)
        else:
            _link_without_clobbering(temp, target)
    finally:
        if temp.exists():
            temp.unlink()
        interrupts.untrack(temp)


def write_file_atomically(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` whole or not at all (`write_atomically` with these bytes)."""
    write_atomically(path, lambda handle: handle.write(data))


def write_atomically(path: str | Path, write) -> None:
    """Write `path` whole or not at all: `write(handle)` fills a temporary file beside it, renamed into place.

    For the many files a command makes in a folder of its own (a dataset's point
    files): an existing `path` is replaced, none of `write_output_bytes`' checks are
    made, and the bytes are not synced to disk. The temporary file (`temporary_name`,
    with this process's id) is removed on an interrupt (`interrupts.track`) and on an
    error; a process killed mid-write leaves it for `remove_temporary_files`.

    Raises
    ------
    OutputFileError
        The file cannot be created or written (its folder is missing, read-only, full).
    """
    target = Path(path)
    temp = _create_temp_file(target)
    try:
        with open(temp, "wb") as handle:
            write(handle)
        os.replace(temp, target)
    except OSError as err:
        raise OutputFileError(f"cannot write {target}: {err.strerror or err}") from None
    finally:
        if os.path.lexists(temp):
            os.unlink(temp)
        interrupts.untrack(temp)


def is_stream(path: str | Path) -> bool:
    """Whether `path` is an existing character device or FIFO (through symlinks).

    Raises
    ------
    OutputFileError
        `path` is a block device or a socket: no point cloud is written there.
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return False
    if stat.S_ISBLK(mode) or stat.S_ISSOCK(mode):
        kind = "a block device" if stat.S_ISBLK(mode) else "a socket"
        raise OutputFileError(f"cannot write {path}: it is {kind}, not a file")
    return stat.S_ISCHR(mode) or stat.S_ISFIFO(mode)


def _write_stream(path: Path, data: bytes) -> None:
    """All of `data` into a character device or FIFO, opened for writing only (never created)."""
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError as err:
        raise OutputFileError(f"cannot write {path}: {err.strerror or err}") from None
    try:
        _write_to_descriptor(fd, data, f"cannot write {path}")
    finally:
        os.close(fd)


def _write_to_descriptor(fd: int, data: bytes, what: str) -> None:
    """Every byte of `data` to `fd`, across short writes; a reader that has gone raises
    BrokenPipeError, any other failure OutputFileError starting with `what`."""
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
    except BrokenPipeError:
        raise
    except OSError as err:
        raise OutputFileError(f"{what}: {err.strerror or err}") from None


def _write_through_links(target: Path) -> Path:
    """The file a write to `target` lands in: `target`, or what its chain of symlinks names."""
    if not target.is_symlink():
        return target
    try:
        return Path(os.path.realpath(target, strict=False))
    except (OSError, ValueError):
        return target


def _nearest_existing(directory: Path) -> Path:
    """`directory`, or its closest ancestor that exists (what a mkdir -p would write into)."""
    directory = Path(os.path.abspath(directory))
    while not directory.exists() and directory != directory.parent:
        directory = directory.parent
    return directory


def _identity(stat: os.stat_result) -> tuple[int, int]:
    return stat.st_dev, stat.st_ino


def _input_clash(target: Path, source) -> str:
    if str(target) == str(source):
        return f"{target} is also an input"
    return f"{target} is the same file as the input {source}"


def _check_not_read(target: Path) -> None:
    if _inputs_read is None:
        return
    try:
        identity = _identity(os.stat(target))
    except OSError:
        return  # not there (yet): nothing to destroy
    if identity in _inputs_read:
        raise OutputFileError(f"{target} is one of the inputs: {NEVER_OVER_INPUTS}")


def _write_stdout(data: bytes) -> None:
    """All of `data` to stdout: through its file descriptor when it has one (a short write
    to a pipe whose reader has gone must end in EPIPE, not in silently dropped bytes)."""
    stream = sys.stdout
    try:
        stream.flush()
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):  # an in-memory stream (tests): no descriptor
            stream.buffer.write(data)
            stream.buffer.flush()
            return
    except BrokenPipeError:
        raise
    except OSError as err:
        raise OutputFileError(f"cannot write to stdout: {err.strerror or err}") from None
    _write_to_descriptor(fd, data, "cannot write to stdout")


def check_writable_folder(folder: str | Path, *, create: bool = False) -> None:
    """Make sure files can be created in `folder` (with `create`, making it and its parents first).

    A command calls this before any work so that an unwritable output folder is reported
    at once, not after the computation. Beyond `check_output_folder` it creates and
    removes one empty temporary file, which also catches what permission bits do not
    show (a read-only file system, a root user without rights there).

    Raises
    ------
    OutputFileError
        `folder` is a file, is missing (without `create`) or cannot be made, or takes no
        new files.
    """
    folder = Path(folder)
    if not folder.exists() and not create:
        raise OutputFileError(f"cannot write to {folder}: the folder does not exist")
    check_output_folder(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise OutputFileError(f"cannot create output folder {folder}: {err.strerror or err}") from None
    probe = _create_temp_file(folder / "escape-write-check", f"cannot write to folder {folder}")
    probe.unlink()
    interrupts.untrack(probe)


def _create_temp_file(target: Path, what: str | None = None) -> Path:
    """Create an empty, exclusive temporary file beside `target` (umask applies), named by `temporary_name`.

    An interrupt removes it (`escape_cli.interrupts.track`) until the caller, having
    renamed or removed it, calls `interrupts.untrack`. `what` starts the error message
    (default: "cannot write TARGET").
    """
    what = what or f"cannot write {target}"
    for attempt in range(100):
        temp = target.with_name(temporary_name(target.name, os.getpid(), attempt))
        interrupts.track(temp)  # before it exists: no moment when it exists untracked
        try:
            fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            interrupts.untrack(temp)
            continue
        except OSError as err:
            interrupts.untrack(temp)
            raise OutputFileError(f"{what}: {_why_not_created(err, target.parent)}") from None
        os.close(fd)
        return temp
    raise OutputFileError(f"{what}: no free temporary name beside it")


def temporary_name(name: str, pid: int, attempt: int) -> str:
    """The name of the temporary file process `pid` writes `name` into before renaming it."""
    return f".{name}.{pid}.{attempt}.tmp"


TEMPORARY_NAME = re.compile(r"\.(?P<name>.+)\.(?P<pid>[0-9]+)\.[0-9]+\.tmp")


def remove_temporary_files(folder: str | Path, *, pids: Iterable[int] | None = None,
                           names: Iterable[str] | None = None) -> None:
    """Remove the temporary files left in `folder` by processes that were stopped mid-write.

    Only those of the processes `pids`, or (any process) of the outputs `names`; never
    anything else. Errors are ignored: this runs while a stopped batch exits.
    """
    pids = None if pids is None else {str(pid) for pid in pids}
    names = None if names is None else set(names)
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        match = TEMPORARY_NAME.fullmatch(entry.name)
        if match is None or (pids is not None and match["pid"] not in pids):
            continue
        if names is not None and match["name"] not in names:
            continue
        try:
            os.unlink(entry.path)
        except OSError:
            pass


def _why_not_created(err: OSError, folder: Path) -> str:
    """Why a file could not be created in `folder` (which exists), in words."""
    if err.errno == errno.EROFS:
        return f"{folder} is on a read-only file system"
    refused_anyway = isinstance(err, PermissionError) and os.access(folder, os.W_OK | os.X_OK)
    if err.errno == errno.ENOENT or refused_anyway:  # the folder is there and writable: its file system makes no files
        kind = _file_system_type(folder)
        return f"{folder} takes no new files" + (f" (a {kind} file system)" if kind else "")
    if isinstance(err, PermissionError):
        return "permission denied"
    return str(err.strerror or err)


def _read_only(directory: Path) -> bool:
    """Whether `directory` lies on a file system mounted read-only."""
    try:
        return bool(os.statvfs(directory).f_flag & os.ST_RDONLY)
    except (AttributeError, OSError):
        return False


def _file_system_type(path: Path) -> str | None:
    """The type of the file system `path` lies on (Linux: /proc/self/mounts), or None."""
    try:
        lines = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return None
    where = os.path.realpath(path)
    best = None
    for line in lines:
        fields = line.split()
        if len(fields) < 3:
            continue
        mount = fields[1].replace("\\040", " ")
        inside = where == mount or where.startswith(mount.rstrip("/") + "/")
        if inside and (best is None or len(mount) >= len(best[0])):
            best = (mount, fields[2])
    return best[1] if best else None


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
