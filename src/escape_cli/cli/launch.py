"""The `escape` command's entry point: for `escape complete`, the network starts loading first.

A cold `escape complete scan.ply -o out.ply` spends most of its time importing (typer,
numpy, scipy) and building the onnxruntime session. The session builds without the
interpreter lock, so it is started here, in a background thread, before the CLI is
imported, from a look at the raw arguments: the command, and `--model` if given. The
command then joins that load (`inference.preload_model`, `load_model`). A guess that
turns out wrong (the command fails to parse, or names its model another way) costs only
CPU time: nothing here reports an error, and the command loads what it needs itself.
"""

from __future__ import annotations

import sys

from escape_cli.cli.argv import preload_target


def main() -> None:
    """`escape ...`: start the model's load when the command will need it, then run the CLI."""
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
