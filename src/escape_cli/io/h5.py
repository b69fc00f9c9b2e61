"""HDF5 point clouds (``.h5``, as the PCN/Completion3D and MVP releases ship them), through h5py.

A cloud is one 2-D numeric dataset of shape (N, >=3): the one named ``points``,
``xyz`` or ``data`` (in that order), else the only (N, >=3) dataset in the file; its
columns 3.. and the other (N,) datasets beside it are fields. Files that hold a batch
of clouds (B, N, 3), like MVP's ``incomplete_pcds``, are refused with a message that
says so. Writing gives ``points`` (N, 3) plus one float32 (N,) dataset per field.
h5py is the ``h5`` extra (``pip install 'escape-cli[h5]'``).
"""

from __future__ import annotations

import io

import numpy as np

from escape_cli.errors import InputFileError
from escape_cli.extras import require
from escape_cli.io.common import Fields

H5_MAGIC = b"\x89HDF\r\n\x1a\n"
CLOUD_NAMES = ("points", "xyz", "data")


def is_h5(data: bytes) -> bool:
    """True when the bytes start like an HDF5 file."""
    return data.startswith(H5_MAGIC)


def parse_h5(data: bytes, name: str) -> tuple[np.ndarray, Fields]:
    """Read a cloud from HDF5 bytes.

    Parameters
    ----------
    data : bytes
    name : str
        The file name, for messages.

    Returns
    -------
    xyz : (N, 3) float64
        Non-finite rows included.
    fields : dict of str to (N,) float64
        Columns 3.. as ``col3``...; the other (N,) datasets by their names.

    Raises
    ------
    InputFileError
        Not HDF5, corrupt, or no single (N, >=3) dataset.
    MissingDependencyError
        h5py is not installed.
    """
    h5py = require("h5py", "reading .h5 files")
    if not is_h5(data):
        raise InputFileError(f"{name}: not an HDF5 file (no HDF5 signature)")
    try:
        with h5py.File(io.BytesIO(data), "r") as handle:
            shapes = _numeric_shapes(handle, h5py)  # read the shapes first: batches can be large
            key = _cloud_key(shapes, name)
            table = np.asarray(handle[key][()], dtype=np.float64)  # (N, C)
            beside = {k: handle[k][()] for k, shape in shapes.items() if shape == (len(table),) and "/" not in k}
    except InputFileError:
        raise
    except Exception as err:  # OSError, KeyError... from a damaged file
        raise InputFileError(f"{name}: corrupt or truncated HDF5 file ({_first_line(err)})") from None
    fields = {f"col{j}": table[:, j].copy() for j in range(3, table.shape[1])}
    fields.update({k: np.asarray(v, dtype=np.float64) for k, v in beside.items()})
    return np.ascontiguousarray(table[:, :3]), fields


def serialize_h5(points: np.ndarray, fields: Fields, *, coordinate_dtype=np.float32) -> bytes:
    """HDF5 bytes: dataset ``points`` (N, 3) and one float32 (N,) dataset per field."""
    h5py = require("h5py", "writing .h5 files")
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as handle:
        handle.create_dataset("points", data=np.asarray(points, dtype=coordinate_dtype))
        for key, values in fields.items():
            handle.create_dataset(key, data=np.asarray(values, dtype=np.float32))
    return buffer.getvalue()


def _numeric_shapes(handle, h5py) -> dict[str, tuple]:
    """The shape of every numeric dataset in the file, by path (root datasets by their bare names)."""
    found: dict[str, tuple] = {}

    def visit(path, item):
        if isinstance(item, h5py.Dataset) and item.dtype.kind in "biuf":
            found[path] = tuple(item.shape)

    handle.visititems(visit)
    return found


def _cloud_key(shapes: dict[str, tuple], name: str) -> str:
    def is_cloud(shape):
        return len(shape) == 2 and shape[1] >= 3

    for key in CLOUD_NAMES:
        if key in shapes and is_cloud(shapes[key]):
            return key
    clouds = [key for key, shape in shapes.items() if is_cloud(shape)]
    if len(clouds) == 1:
        return clouds[0]
    if len(clouds) > 1:
        raise InputFileError(f"{name}: several (N, 3) datasets ({', '.join(clouds)}); name the cloud 'points'")
    batches = [f"{key} {shape}" for key, shape in shapes.items() if len(shape) == 3 and shape[2] >= 3]
    if batches:
        raise InputFileError(
            f"{name}: holds batches of clouds ({', '.join(batches)}); escape reads one (N, 3) dataset per file"
        )
    raise InputFileError(f"{name}: no (N, 3) dataset in the HDF5 file")


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__
