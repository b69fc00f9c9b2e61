"""Optional dependencies: which extra of the package installs which library, and one line when one is missing.

The runtime (`pip install escape-cli`) completes, encodes, decodes, evaluates and
renders; other jobs need an extra: ``escape-cli[synth]`` (open3d, for
`escape dataset synth`), ``escape-cli[train]`` (torch and onnx, for `escape train`,
`export-onnx`, `average-checkpoints`), ``escape-cli[h5]`` (h5py, for ``.h5`` clouds).
"""

from __future__ import annotations

import importlib

from escape_cli.errors import MissingDependencyError

EXTRA_OF = {"open3d": "synth", "torch": "train", "onnx": "train", "h5py": "h5"}
"""The extra that installs each optional library."""

SYNTH_SYSTEM_LIBRARIES = ("libgl1", "libegl1", "libx11-6", "libusb-1.0-0", "libudev1", "libgomp1")
"""Debian packages open3d loads (`scripts/install_system_deps.sh synth` installs them)."""

TORCH_CPU_HINT = (
    "; for the CPU build of torch, first: pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"
)


def require(module: str, purpose: str):
    """Import and return an optional library, or raise one line naming the extra that installs it.

    Parameters
    ----------
    module : str
        A key of `EXTRA_OF` (``open3d``, ``torch``, ``onnx``, ``h5py``).
    purpose : str
        What needs it, for the message (``escape dataset synth``, ``reading .h5 files``).

    Raises
    ------
    MissingDependencyError
        The library is not installed, or is installed but cannot be loaded (a missing
        system library, such as libGL for open3d).
    """
    extra = EXTRA_OF[module]
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name != module:
            raise MissingDependencyError(f"{purpose} needs {module}, which cannot be imported: {_first_line(err)}") from None
        hint = TORCH_CPU_HINT if module == "torch" else ""
        raise MissingDependencyError(
            f"{purpose} needs {module}, which is not installed: pip install 'escape-cli[{extra}]'{hint}"
        ) from None
    except (ImportError, OSError) as err:  # e.g. libGL.so.1: cannot open shared object file
        system = f" (open3d needs the system libraries {', '.join(SYNTH_SYSTEM_LIBRARIES)})" if extra == "synth" else ""
        raise MissingDependencyError(
            f"{purpose} needs {module}, which is installed but cannot be loaded: {_first_line(err)}{system}"
        ) from None


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__
