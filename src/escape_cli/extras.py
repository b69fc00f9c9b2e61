"""Optional dependencies: which extra of the package installs which library, and one line when one is missing.

``escape-cli[h5]`` (h5py) reads and writes ``.h5`` clouds.
"""

from __future__ import annotations

import importlib

from escape_cli.errors import MissingDependencyError

EXTRA_OF = {"h5py": "h5"}
"""The extra that installs each optional library."""



def require(module: str, purpose: str):
    """Import and return an optional library, or raise one line naming the extra that installs it.

    Parameters
    ----------
    module : str
        A key of `EXTRA_OF` (``h5py``).
    purpose : str
        What needs it, for the message (``reading .h5 files``).

    Raises
    ------
    MissingDependencyError
        The library is not installed, or is installed but cannot be loaded (a missing
        system library).
    """
    extra = EXTRA_OF[module]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name != module:
            raise MissingDependencyError(f"{purpose} needs {module}, which cannot be imported: {_first_line(err)}") from None
        raise MissingDependencyError(
            f"{purpose} needs {module}, which is not installed: pip install 'escape-cli[{extra}]'"
        ) from None
    except (ImportError, OSError) as err:  # e.g. a shared library that cannot be opened
        raise MissingDependencyError(
            f"{purpose} needs {module}, which is installed but cannot be loaded: {_first_line(err)}"
        ) from None


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__
