"""Run the `escape` CLI in-process exactly as the console script does (through `main()`).

`typer.testing.CliRunner` invokes the Typer app, which skips `main()`'s turning of
escape errors into one `escape: error: ...` line; `run_escape` calls `main()` itself
with `sys.argv` patched and captures the exit code, stdout bytes and stderr text.
"""

from __future__ import annotations

import io
import logging
import sys
from dataclasses import dataclass


@dataclass(frozen=True)
class CliResult:
    exit_code: int
    stdout: bytes
    stderr: str

    @property
    def stderr_lines(self) -> list[str]:
        return self.stderr.splitlines()


def run_escape(*args: str, stdin: bytes = b"") -> CliResult:
    """Run ``escape ARGS...`` in this process; stdin gets `stdin`.

    Returns
    -------
    CliResult
        exit_code 0 on success; stdout as bytes (data may be binary); stderr as text.
    """
    from escape_cli.cli.main import main

    saved = (sys.argv, sys.stdin, sys.stdout, sys.stderr)
    root = logging.getLogger()
    saved_logging = (root.handlers[:], root.level)
    stdout_bytes, stderr_bytes = io.BytesIO(), io.BytesIO()
    sys.argv = ["escape", *map(str, args)]
    sys.stdin = io.TextIOWrapper(io.BytesIO(stdin))
    sys.stdout = io.TextIOWrapper(stdout_bytes, write_through=True)
    sys.stderr = io.TextIOWrapper(stderr_bytes, write_through=True)
    exit_code = 0
    try:
        main()
    except SystemExit as exit_:
        code = exit_.code
        exit_code = code if isinstance(code, int) else (0 if code is None else 1)
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        # read before restoring: dropping the wrappers closes the buffers under them
        stdout, stderr = stdout_bytes.getvalue(), stderr_bytes.getvalue()
        sys.argv, sys.stdin, sys.stdout, sys.stderr = saved
        root.handlers[:] = saved_logging[0]  # main's basicConfig(force=True) replaced them
        root.setLevel(saved_logging[1])
    return CliResult(exit_code, stdout, stderr.decode("utf-8", errors="replace"))
