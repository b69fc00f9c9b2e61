"""A worker process and the parent's end of its pipe: send it work, read its answer, say how it died, stop it.

The base of the dataset commands' workers (`data.workers`) and of the batch engine's
(`engines.local`). Nothing here waits on a dead process: a send to one is dropped (the
caller's wait on the process sentinel sees the death), and a read from one gives None.
"""

from __future__ import annotations

import signal

STOP_SECONDS = 10.0
"""How long a stopping (or dead) worker is waited for before it is killed."""


class PipedProcess:
    """A started `multiprocessing` process and the parent's end of its duplex pipe."""

    def __init__(self, conn, process):
        self.conn, self.process = conn, process

    def send(self, message) -> None:
        try:
            self.conn.send(message)
        except OSError:  # it died already: the caller's wait sees it
            pass

    def answer(self):
        """The message it sent back, or None when there is none (it died)."""
        try:
            if self.conn.poll():
                return self.conn.recv()
        except (EOFError, OSError):
            pass
        return None

    def death(self) -> str:
        """How the process ended, in words (after it died)."""
        self.process.join(STOP_SECONDS)
        code = self.process.exitcode
        self.conn.close()
        if code is None:
            self.process.kill()
            self.process.join()
            return "stopped answering"
        if code < 0:
            try:
                return f"killed by {signal.Signals(-code).name}"
            except ValueError:
                return f"killed by signal {-code}"
        return f"exit code {code}"

    def stop(self, gently: bool) -> None:
        """Ask it to finish (None down the pipe) and wait when `gently`; kill it if it is still alive."""
        if gently:
            self.send(None)
            self.process.join(STOP_SECONDS)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()
