"""Standard streams the caller closed (`escape ... >&-`, `2>&-`, `<&-`), the way GNU tools treat them.

A closed descriptor 0, 1 or 2 would be taken by the first file escape opens, and what
is printed for stdout or stderr would land in that file (Python itself sets
`sys.stdout` to None, and `print(file=None)` writes to stdout). `reopen_closed` puts
/dev/null under each closed one, opened so that it behaves as closed for escape's use
of it: stdin write-only and stdout read-only (reading the one or writing the other
fails with EBADF, so a command that has to print says so in one line and exits 1, and
a command with nothing to print succeeds), stderr write-only (messages vanish; the exit
code and the data are what they would have been).
"""

from __future__ import annotations

import errno
import os
import sys

STREAMS = ((0, "stdin", os.O_WRONLY), (1, "stdout", os.O_RDONLY), (2, "stderr", os.O_WRONLY))

closed: frozenset[str] = frozenset()
"""The standard streams that were closed when the process started (after `reopen_closed`)."""


def reopen_closed() -> frozenset[str]:
    """Put /dev/null under every closed standard descriptor and give Python a stream on it; returns their names."""
    global closed
    found = set()
    for fd, name, flags in STREAMS:
        if _is_open(fd):
            continue
        opened = os.open(os.devnull, flags)
        if opened != fd:  # the lowest free number is fd itself unless a lower one is closed too
            os.dup2(opened, fd)
            os.close(opened)
        found.add(name)
        if getattr(sys, name) is None:
            setattr(sys, name, _stream(fd, name))
    closed = frozenset(found)
    return closed


def is_closed_stdout_error(err: OSError) -> bool:
    """Whether `err` is a write to a stdout the caller had closed."""
    return "stdout" in closed and err.errno == errno.EBADF


def _is_open(fd: int) -> bool:
    try:
        os.fstat(fd)
    except OSError:
        return False
    return True


def _stream(fd: int, name: str):
    """A text stream on `fd` like the one Python makes at start-up (stderr line-buffered, errors escaped)."""
    if name == "stdin":
        return open(fd, "r", closefd=False)  # noqa: SIM115 (lives as long as the process)
    if name == "stderr":
        return open(fd, "w", buffering=1, errors="backslashreplace", closefd=False)  # noqa: SIM115
    return open(fd, "w", closefd=False)  # noqa: SIM115
