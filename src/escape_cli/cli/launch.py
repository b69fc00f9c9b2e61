"""The `escape` command's entry point: signals and closed streams first, then, for `escape complete`, the network's load.

Its first statements make Ctrl-C and SIGTERM end the process with one line and 130 or
143 at any moment from here on (`escape_cli.interrupts`), and put /dev/null under any
standard descriptor the caller closed (`cli.streams`), before anything heavy is
imported.

A cold `escape complete scan.ply -o out.ply` spends most of its time importing (typer,
numpy, scipy) and building the onnxruntime session. The session builds without the
interpreter lock, so it is started here, in a background thread, before the CLI is
imported, from a look at the raw arguments: the command, and `--model` if given. The
command then joins that load (`inference.preload_model`, `load_model`). A guess that
turns out wrong (the command fails to parse, or names its model another way) costs only
CPU time: nothing here reports an error, and the command loads what it needs itself.
"""

from __future__ import annotations

import escape_cli.interrupts as interrupts

interrupts.install()  # first: an interrupt during the imports below is one line too

import sys  # noqa: E402

from escape_cli.cli.argv import preload_target  # noqa: E402
from escape_cli.cli.streams import reopen_closed  # noqa: E402


def main() -> None:
    """`escape ...`: start the model's load when the command will need it, then run the CLI."""
    reopen_closed()
    wanted, model = preload_target(sys.argv[1:])
    loading = None
    if wanted:
        from escape_cli.inference import preload_model

        loading = preload_model(model)
    try:
        from escape_cli.cli.main import main as run_cli

        run_cli()
    finally:
        if loading is not None:
            from concurrent.futures import wait

            wait([loading])  # never leave the loader running at exit


if __name__ == "__main__":
    main()
