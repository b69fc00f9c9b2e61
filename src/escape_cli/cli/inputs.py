"""Turning command-line inputs (files, folders, globs, '-') into a list of cloud files."""

from __future__ import annotations

import glob
from pathlib import Path

from escape_cli.errors import InputFileError
from escape_cli.io import CLOUD_SUFFIXES


def expand_inputs(items: list[str], recursive: bool = False) -> list[str]:
    """Files named, every cloud file in named folders, and glob matches, in the order given.

    '-' (stdin) is kept as is. A name that is neither a file, a folder nor a matching glob
    is kept too, so that reading it reports the problem for that file alone.
    """
    out: list[str] = []
    for item in items:
        if item == "-":
            out.append(item)
            continue
        path = Path(item)
        if path.is_dir():
            pattern = "**/*" if recursive else "*"
            found = sorted(p for p in path.glob(pattern) if p.is_file() and p.suffix.lower() in CLOUD_SUFFIXES)
            if not found:
                raise InputFileError(f"no point-cloud files ({', '.join(CLOUD_SUFFIXES)}) in folder {item}")
            out.extend(str(p) for p in found)
        elif not path.exists() and glob.has_magic(item):
            matches = sorted(glob.glob(item, recursive=True))
            if not matches:
                raise InputFileError(f"no files match {item}")
            out.extend(m for m in matches if Path(m).is_file())
        else:
            out.append(item)
    if out.count("-") > 1:
        raise InputFileError("stdin ('-') can be read only once")
    return out
