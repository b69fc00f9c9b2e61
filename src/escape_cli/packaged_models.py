"""The models packaged with escape, by name, and what a `--model` value names.

A packaged model is a file ``escape-<name>.onnx`` (with its ``escape-<name>.json``
metadata) in the package folder ``escape_cli/models``: ``small`` is the default. A
`--model` value (or ``$ESCAPE_MODEL``) is a path or a name:

- an existing file is a path, whatever it is called;
- otherwise a bare word (letters, digits, ``-`` and ``_``) is a packaged model's name,
  and a word that names none is refused with the names there are;
- anything else (``./m.onnx``, ``runs/best.onnx``) is a path.

Listing the names reads one folder and imports nothing heavy, so ``--help`` lists
them. Test hook: ``$ESCAPE_TEST_MODELS`` replaces the package folder (the tests' own
packaged models).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from escape_cli.errors import ModelError

DEFAULT = "small"
"""The packaged model used when neither `--model` nor ``$ESCAPE_MODEL`` says otherwise."""
MODEL_ENV = "ESCAPE_MODEL"
FOLDER_ENV = "ESCAPE_TEST_MODELS"
PREFIX, SUFFIX = "escape-", ".onnx"
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_-]*")
"""What a packaged model's name looks like (and what a `--model` value must be to be read as one)."""


def folder():
    """Where the packaged models are: ``escape_cli/models``, a `Path` when the package is a folder.

    The folder beside this module when it is one (no import: `--help` calls this);
    else `importlib.resources` says (a package imported from a zip gives a non-`Path`).
    """
    override = os.environ.get(FOLDER_ENV)
    if override:
        return Path(override)
    here = Path(__file__).parent
    if here.is_dir():
        return here / "models"
    from importlib import resources

    return resources.files("escape_cli") / "models"


def names() -> list[str]:
    """The packaged models' names, sorted (the default first): the ``escape-<name>.onnx`` files of `folder`."""
    try:
        files = [entry.name for entry in folder().iterdir()]
    except OSError:
        files = []
    found = {f[len(PREFIX):-len(SUFFIX)] for f in files if f.startswith(PREFIX) and f.endswith(SUFFIX)}
    found = {name for name in found if NAME.fullmatch(name)}
    return sorted(found, key=lambda name: (name != DEFAULT, name))


def listing() -> str:
    """The names for a help text or a message: ``small, synth`` (``none`` when there is none)."""
    return ", ".join(names()) or "none"


def is_name(value: str) -> bool:
    """Whether `value` reads as a model's name rather than a path (a bare word)."""
    return bool(NAME.fullmatch(value))


def path_of(name: str) -> Path:
    """The file of packaged model `name`; ModelError (with the names there are) when there is none."""
    resource = folder() / f"{PREFIX}{name}{SUFFIX}"
    if not isinstance(resource, Path):  # a package imported from a zip: onnxruntime needs a real file
        raise ModelError(f"the packaged models are not on the file system ({resource}); pass --model PATH or set {MODEL_ENV}")
    if not resource.is_file():
        if name == DEFAULT and not names():
            raise ModelError(f"no model found: {resource} is missing (pass --model or set {MODEL_ENV})")
        here = f"{name} is a folder, and " if os.path.isdir(name) else ""
        raise ModelError(f"{here}no packaged model is named {name!r} (packaged models: {listing()}); "
                         f"give one of those names or a model file's path")
    return resource


def resolve(value: str | os.PathLike | None) -> Path:
    """The model file that `value` names: a path, a packaged model's name, or None.

    None means ``$ESCAPE_MODEL`` (itself a path or a name) when set, else the default
    packaged model. An existing file is a path; a bare word (`is_name`) is a packaged
    model's name (ModelError listing the names when none is called so, even where a
    folder of that name exists); anything else is returned as a path, for
    `inference.read_metadata` to check.
    """
    env = os.environ.get(MODEL_ENV) if value is None else None
    text = os.fspath(value) if value is not None else (env or DEFAULT)
    if os.path.isfile(text) or not is_name(text):
        return Path(text)
    try:
        return path_of(text)
    except ModelError as err:
        if env:
            raise ModelError(f"${MODEL_ENV} is {text!r}: {err}") from None
        raise


__all__ = ["DEFAULT", "FOLDER_ENV", "MODEL_ENV", "folder", "is_name", "listing", "names", "path_of", "resolve"]
