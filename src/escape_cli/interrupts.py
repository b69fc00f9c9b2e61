"""Ctrl-C and SIGTERM in the `escape` command: one line, its exit code, nothing half-written left.

`install` (the first thing the entry point does) makes SIGINT and SIGTERM end the
process at once, whatever it is doing: the cleanups registered with `on_interrupt` run
(a batch stops its worker processes and removes their temporary files), every
temporary file registered with `track` is removed, ``escape: interrupted`` is written
on stderr, and the process exits with 128 + the signal (130 for SIGINT, 143 for
SIGTERM) through `os._exit`: no exception is raised, so no traceback, half-finished
import or exit handler can follow. Finished outputs stay (they were renamed into place
whole). A signal that comes once the command has finished, while the interpreter tears
itself down, is ignored: the process exits as it finished. The handler runs between any
two bytecodes of the main thread, from the entry point's first line on; a signal that
arrives while native code runs (a forward pass, a big numpy call) is handled as soon as
that call returns.

Library code only registers here; in a process that did not call `install` (a Python
program using escape, the test runner) nothing changes.

This module is imported before anything else, so it imports only what the interpreter
has already loaded, and the C half of `signal` (the `signal` module itself imports enum:
milliseconds during which an interrupt would still be a traceback).
"""

from __future__ import annotations

import os
import sys

import _signal

MESSAGE = b"escape: interrupted\n"
SIGNALS = (_signal.SIGINT, _signal.SIGTERM)

_temporary: set = set()  # paths of temporary files (str)
_cleanups: list = []  # callables, run most recent first
_installed = False
_handled: tuple = ()  # the signals handled: those not ignored when `install` was first called
_held = 0  # depth of `deferred` blocks
_pending = None  # a signal number that came within one


def install() -> None:
    """Handle SIGINT and SIGTERM in this process as the module docstring says (from the main thread).

    A signal the process was started with ignored (``nohup``, a background job of a
    script) stays ignored, as the interpreter itself leaves it.
    """
    global _installed, _handled
    if not _installed:
        _handled = tuple(signum for signum in SIGNALS if _signal.getsignal(signum) != _signal.SIG_IGN)
        _installed = True
        import atexit  # built in: no import of Python code

        atexit.register(_ignore_signals)  # registered first, so it runs last
    for signum in _handled:
        _signal.signal(signum, _interrupted)


def _ignore_signals() -> None:
    """At exit, after every other exit handler: ignore SIGINT and SIGTERM from here on.

    The interpreter then tears down its modules (open3d's, torch's: up to a second) after
    putting back the default action of every signal that had a Python handler, so a
    signal in that window would kill the process silently, with no line and no exit
    code of ours. The command's work is done by then: the process exits as it finished.
    """
    for signum in _handled:
        _signal.signal(signum, _signal.SIG_IGN)


def installed() -> bool:
    """Whether `install` was called in this process (a library that sets its own handlers calls it again)."""
    return _installed


def interrupt(signum: int) -> None:
    """End the process now as if signal `signum` had come (for a library's handler that got it first)."""
    _interrupted(signum, None)


def track(path) -> None:
    """Remove `path` if the process is interrupted before `untrack` (call it before creating the file)."""
    _temporary.add(os.fspath(path))


def untrack(path) -> None:
    _temporary.discard(os.fspath(path))


class on_interrupt:
    """``with on_interrupt(cleanup):`` an interrupt within the block runs `cleanup()` before the process exits."""

    def __init__(self, cleanup):
        self.cleanup = cleanup

    def __enter__(self):
        _cleanups.append(self.cleanup)
        return self

    def __exit__(self, *exc) -> None:
        if self.cleanup in _cleanups:
            _cleanups.remove(self.cleanup)


class deferred:
    """``with deferred():`` an interrupt within the block is handled as it ends; a process started
    in it starts with SIGINT blocked.

    A worker process is started this way: the parent never dies half-way through handing
    it its start-up data (which the worker would report with a traceback), and a Ctrl-C
    typed at the terminal, which reaches every process of the group, never reaches the
    worker, even while its interpreter starts: the parent alone handles it, and stops
    the worker.
    """

    def __enter__(self):
        global _held
        self.mask = _signal.pthread_sigmask(_signal.SIG_BLOCK, {_signal.SIGINT}) if _MASKS else None
        _held += 1
        return self

    def __exit__(self, *exc) -> None:
        global _held
        _held -= 1
        if self.mask is not None:
            _signal.pthread_sigmask(_signal.SIG_SETMASK, self.mask)
        if not _held and _pending is not None:
            _interrupted(_pending, None)


_MASKS = hasattr(_signal, "pthread_sigmask")


def _interrupted(signum: int, frame) -> None:
    global _pending
    if _held:
        _pending = signum
        return
    for other in SIGNALS:  # a second Ctrl-C must not cut the clean-up short
        _signal.signal(other, _signal.SIG_IGN)
    for cleanup in reversed(list(_cleanups)):
        try:
            cleanup()
        except BaseException:  # noqa: BLE001 (exiting anyway; the other clean-ups still run)
            pass
    for path in list(_temporary):
        try:
            os.unlink(path)
        except OSError:
            pass
    if not _in_a_worker():  # the command says it once; its workers end quietly
        try:
            sys.stderr.flush()
        except BaseException:  # noqa: BLE001 (stderr closed or broken: the exit code still says it)
            pass
        try:
            os.write(2, MESSAGE)
        except OSError:
            pass
    os._exit(128 + signum)


def _in_a_worker() -> bool:
    """Whether this process is a worker started by `multiprocessing` (which imports the entry point again)."""
    mp = sys.modules.get("multiprocessing")
    return mp is not None and mp.parent_process() is not None
