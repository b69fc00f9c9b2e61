"""What the raw command line (sys.argv[1:]) says before typer parses it: for the entry point and the usage errors."""

from __future__ import annotations

GLOBAL_OPTIONS = ("-q", "--quiet", "-v", "-vv", "-vvv", "--verbose", "--version")
# Options after which `complete` may run several scans, in other processes: no preload.
BATCH_OPTIONS = ("--workers", "-w", "--files-from", "--engine", "--shard", "-h", "--help")


def preload_target(args: list[str]) -> tuple[bool, str | None]:
    """Whether `args` look like `escape complete` of one scan, and its `--model` (None: the default)."""
    rest = list(args)
    while rest and rest[0] in GLOBAL_OPTIONS:
        rest.pop(0)
    if not rest or rest[0] != "complete":
        return False, None
    model = None
    for i, token in enumerate(rest[1:], start=1):
        name = token.split("=", 1)[0]
        if name in BATCH_OPTIONS:
            return False, None
        if name in ("--model", "-m"):
            if "=" in token:
                model = token.split("=", 1)[1]
            elif i + 1 < len(rest):
                model = rest[i + 1]
    return True, model
