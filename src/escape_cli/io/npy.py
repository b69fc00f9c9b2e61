"""NumPy files: point clouds as (N, 3) or (N, >=3) arrays in .npy / .npz, and plain arrays.

A cloud in a ``.npz`` is the array named ``points`` (or ``xyz``, or the only array);
the other (N,) arrays in it are fields. `parse_array` / `serialize_array` carry any
array (the distance matrices of ``escape encode``/``decode``).
"""

from __future__ import annotations

import io

import numpy as np

from escape_cli.errors import InputFileError
from escape_cli.io.common import Fields, storage_dtype

NPY_MAGIC = b"\x93NUMPY"
NPZ_MAGIC = b"PK\x03\x04"
CLOUD_KEYS_IN_NPZ = ("points", "xyz")


def is_npy(data: bytes) -> bool:
    return data.startswith(NPY_MAGIC)


def is_npz(data: bytes) -> bool:
    return data.startswith(NPZ_MAGIC)


def parse_array(data: bytes, name: str) -> np.ndarray:
    """The array stored in ``.npy`` bytes (no pickles).

    Raises
    ------
    InputFileError
        Empty, not an .npy file, truncated or corrupt, or an object array.
    """
    if not data:
        raise InputFileError(f"{name}: empty file")
    if not is_npy(data):
        raise InputFileError(f"{name}: not a .npy file (no NumPy magic bytes)")
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read_header(stream)  # 2.0 and 3.0 headers have the same layout
    except Exception as err:  # numpy raises ValueError, SyntaxError, TokenError... on bad headers
        raise InputFileError(f"{name}: corrupt .npy header ({_first_line(err)})") from None
    needed = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize if not dtype.hasobject else 0
    found = len(data) - stream.tell()
    if found < needed:
        raise InputFileError(f"{name}: corrupt or truncated .npy file ({needed} data bytes needed, {found} found)")
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as err:  # object arrays, odd dtypes: anything np.load refuses
        raise InputFileError(f"{name}: corrupt or truncated .npy file ({_first_line(err)})") from None
    if not np.issubdtype(array.dtype, np.number) and array.dtype != np.bool_:
        raise InputFileError(f"{name}: .npy array has non-numeric dtype {array.dtype}")
    _refuse_complex(array, name)
    return array


def serialize_array(array: np.ndarray) -> bytes:
    """``.npy`` bytes of an array."""
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array), allow_pickle=False)
    return buffer.getvalue()


def parse_npy(data: bytes, name: str, fmt: str = "npy") -> tuple[np.ndarray, Fields]:
    """Read a cloud from ``.npy`` or ``.npz`` bytes (told apart by their first bytes).

    Parameters
    ----------
    data : bytes
    name : str
        The file name, for messages.
    fmt : str
        "npy" or "npz": what the file was read as (by its name), for messages.

    Returns
    -------
    xyz : (N, 3) float64
        Columns 0-2, non-finite rows included.
    fields : dict of str to (N,) float64
        Columns 3.. as ``col3``, ``col4``...; in an npz, also its other (N,) arrays.

    Raises
    ------
    InputFileError
        Corrupt file, or an array that is not (N, >=3).
    """
    extra: dict[str, np.ndarray] = {}
    if fmt == "npz" and not (is_npz(data) or is_npy(data)):
        raise InputFileError(f"{name}: not a .npz file (no zip archive signature)")
    if is_npz(data):
        array, extra = _cloud_from_npz(data, name)
    else:
        array = parse_array(data, name)
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputFileError(f"{name}: array of shape {array.shape}; expected (N, 3) or (N, >=3)")
    table = array.astype(np.float64)
    fields = {f"col{j}": table[:, j].copy() for j in range(3, table.shape[1])}
    fields.update({key: value for key, value in extra.items() if value.shape == (len(table),)})
    return np.ascontiguousarray(table[:, :3]), fields


def serialize_npy(points: np.ndarray, *, coordinate_dtype=np.float32) -> bytes:
    """``.npy`` bytes of the (N, 3) coordinates (fields are not stored)."""
    return serialize_array(np.asarray(points, dtype=coordinate_dtype))


def serialize_npz(points: np.ndarray, fields: Fields, *, coordinate_dtype=np.float32) -> bytes:
    """``.npz`` bytes: ``points`` (N, 3) plus one float32 (N,) array per field (float64 where needed)."""
    buffer = io.BytesIO()
    arrays = {"points": np.asarray(points, dtype=coordinate_dtype)}
    arrays.update({key: np.asarray(value, dtype=storage_dtype(value)) for key, value in fields.items()})
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def _cloud_from_npz(data: bytes, name: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    except Exception as err:  # BadZipFile, zlib.error, ValueError, EOFError... from a damaged archive
        raise InputFileError(f"{name}: corrupt or truncated .npz file ({_first_line(err)})") from None
    key = next((k for k in CLOUD_KEYS_IN_NPZ if k in arrays), None)
    if key is None and len(arrays) == 1:
        key = next(iter(arrays))
    if key is None:
        raise InputFileError(f"{name}: .npz holds {sorted(arrays)}; expected an array named 'points'")
    cloud = arrays.pop(key)
    if not np.issubdtype(cloud.dtype, np.number):
        raise InputFileError(f"{name}: array '{key}' has non-numeric dtype {cloud.dtype}")
    _refuse_complex(cloud, f"{name}: array '{key}'")
    extra = {
        k: v.astype(np.float64) for k, v in arrays.items() if np.issubdtype(v.dtype, np.number) and v.dtype.kind != "c"
    }
    return cloud, extra


def _refuse_complex(array: np.ndarray, name: str) -> None:
    """Complex numbers are no coordinates: casting would drop the imaginary parts unseen."""
    if array.dtype.kind == "c":
        raise InputFileError(f"{name} holds complex numbers ({array.dtype}); real coordinates or distances are expected")


def _first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__
