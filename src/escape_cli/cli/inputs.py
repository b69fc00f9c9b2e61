"""Turning command-line inputs (files, folders, globs, '-') into a list of cloud files."""

from __future__ import annotations

import glob
import logging
from pathlib import Path

from escape_cli.errors import InputFileError
from escape_cli.io import CLOUD_SUFFIXES

log = logging.getLogger("escape")
SKIPPED_NAMES_SHOWN = 5


def expand_inputs(items: list[str], recursive: bool = False) -> list[str]:
    """Files named, every cloud file in named folders, and glob matches, in the order given.

    '-' (stdin) is kept as is. Files named and glob matches are kept whatever they are
    called (reading them reports what they are not); a folder gives only its point-cloud
    files (`folder_clouds`). A name that is neither a file, a folder nor a matching glob
    is kept too, so that reading it reports the problem for that file alone.
    """
    out: list[str] = []
    for item in items:
        if item == "-":
            out.append(item)
            continue
        path = Path(item)
        if path.is_dir():
            out.extend(folder_clouds(path, recursive))
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


def folder_clouds(folder: Path, recursive: bool = False) -> list[str]:
    """The point-cloud files in `folder`, sorted: a known extension, and text files whose first
    row is numbers (`io.is_cloud_file`); the others are skipped, counted in a -v log line."""
    from escape_cli.io import is_cloud_file

    pattern = "**/*" if recursive else "*"
    found, skipped = [], []
    for path in sorted(p for p in folder.glob(pattern) if p.is_file()):
        (found if is_cloud_file(path) else skipped).append(path)
    if skipped:
        names = ", ".join(str(p.relative_to(folder)) for p in skipped[:SKIPPED_NAMES_SHOWN])
        more = f" and {len(skipped) - SKIPPED_NAMES_SHOWN} more" if len(skipped) > SKIPPED_NAMES_SHOWN else ""
        log.info("%s: skipped %d file(s) that are not point clouds (%s%s)", folder, len(skipped), names, more)
    if not found:
        raise InputFileError(f"no point-cloud files ({', '.join(CLOUD_SUFFIXES)}) in folder {folder}")
    return [str(p) for p in found]
