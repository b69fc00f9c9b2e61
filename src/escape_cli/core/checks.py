"""The one boundary check of the package: coerce and validate arrays and parameters.

Every public function that takes points, distances or anchors calls `as_points` or
`as_rows` first; what is below it trusts its input. Any array-like is accepted, and so
are point-cloud objects of other libraries, by duck typing (nothing is imported): an
object with a ``points`` attribute (`open3d.geometry.PointCloud`, escape's own results)
or a ``vertices`` attribute (`trimesh.PointCloud`, `trimesh.Trimesh`) stands for that
array. Bad arrays raise `PointCloudError`
with one wording (scalar parameters are checked by `escape_cli.core.params`):

    "<name> must be an array of numbers (got str)"
    "<name> must have shape (N, 3), not shape (5, 2)"
    "<name> is empty (no points)"
    "<name> has 3 points; at least 16 are needed"
    "NaN or infinite values in <name>"
    "<name> has values up to 1e+300; at most 1e+150 can be used"
"""

from __future__ import annotations

import numpy as np

from escape_cli.errors import DegenerateGeometryError, PointCloudError

CLOUD_ATTRIBUTES = ("points", "vertices")
"""Attributes that hold the (N, 3) array of a point-cloud object (open3d, trimesh)."""

MAX_MAGNITUDE = 1e150
"""Largest usable |value|: its square (a squared distance) must stay finite in float64."""

COLLINEAR_RTOL = 1e-3
"""Points (or anchors) are (nearly) collinear when the second singular value of their
centred coordinates is below this share of the largest: the angle about the line is
then lost in the distances."""


def as_rows(values, name: str, columns: int | None = 3, min_rows: int = 0, letters: str = "NC") -> np.ndarray:
    """Coerce to a finite `(N, columns) float64` array with at least `min_rows` rows.

    Parameters
    ----------
    values : array_like, or an object with a ``points`` / ``vertices`` array attribute
    name : str
        What the array is, for the message ("input cloud", "anchors", "distances").
    columns : int or None
        Required number of columns; None accepts any (at least 1).
    min_rows : int
    letters : str
        Shape letters for the message, from the package legend ("NC": (N, 3); "MK": (M, K)).

    Returns
    -------
    (N, C) float64, C-contiguous (a new array only where coercion needed one).

    Raises
    ------
    PointCloudError
    """
    arr = _numeric(values, name)
    shape = f"({letters[0]}, {columns if columns else letters[1]})"
    if arr.ndim != 2 or (columns is not None and arr.shape[1] != columns) or arr.shape[1] == 0:
        raise PointCloudError(f"{name} must have shape {shape}, not shape {arr.shape}")
    if len(arr) < min_rows:
        noun = "points" if columns == 3 else "rows"
        if len(arr) == 0:
            raise PointCloudError(f"{name} is empty (no {noun})")
        raise PointCloudError(f"{name} has {len(arr)} {noun}; at least {min_rows} are needed")
    _check_values(arr, name)
    return np.ascontiguousarray(arr)


def as_points(points, name: str = "points", min_points: int = 1) -> np.ndarray:
    """Coerce to a finite `(N, 3) float64` array with at least `min_points` rows (see `as_rows`)."""
    return as_rows(points, name, 3, min_points)


def as_vector(value, name: str, size: int = 3) -> np.ndarray:
    """Coerce to a finite `(size,) float64` vector, e.g. a translation or an axis."""
    arr = _numeric(value, name).reshape(-1)
    if arr.shape != (size,):
        raise PointCloudError(f"{name} must be {size} numbers, got shape {np.shape(value)}")
    _check_values(arr, name)
    return arr


def check_not_collinear(points: np.ndarray, name: str = "the points") -> None:
    """Raise DegenerateGeometryError when `points` (N, 3) are all equal or (nearly) on one line."""
    points = as_points(points, name, min_points=1)
    centred = points - points.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)  # (3,) descending
    if not sv[0] > 0:
        raise DegenerateGeometryError(f"{name} are all identical")
    if sv[1] < COLLINEAR_RTOL * sv[0]:
        raise DegenerateGeometryError(
            f"{name} are (nearly) collinear: singular values {sv[0]:.3g}, {sv[1]:.3g}, {sv[2]:.3g}"
        )


def _unwrap_cloud(values):
    """The array inside a point-cloud object (its ``points``, else ``vertices``), else `values` itself.

    open3d's ``PointCloud.points`` is a ``Vector3dVector`` and trimesh's
    ``PointCloud.vertices`` a ``TrackedArray``: both become arrays under `np.asarray`.
    """
    if isinstance(values, (np.ndarray, list, tuple, str, bytes)):
        return values
    for attribute in CLOUD_ATTRIBUTES:
        inner = getattr(values, attribute, None)
        if inner is not None and not callable(inner):
            return inner
    return values


def _numeric(values, name: str) -> np.ndarray:
    values = _unwrap_cloud(values)
    if isinstance(values, (str, bytes)):
        raise PointCloudError(f"{name} must be an array of numbers (got {type(values).__name__})")
    try:
        raw = np.asarray(values)
    except (ValueError, TypeError):  # ragged nesting
        raise PointCloudError(f"{name} must be an array of numbers with one length per row") from None
    if raw.dtype.kind not in "biuf":
        raise PointCloudError(f"{name} must be an array of numbers (got {raw.dtype.name if raw.dtype.kind != 'O' else 'objects'})")
    return raw.astype(np.float64, copy=False)


def _check_values(arr: np.ndarray, name: str) -> None:
    if arr.size == 0:
        return
    largest = float(np.max(np.abs(arr)))  # NaN propagates
    if not np.isfinite(largest):
        raise PointCloudError(f"NaN or infinite values in {name}")
    if largest > MAX_MAGNITUDE:
        raise PointCloudError(f"{name} has values up to {largest:.3g}; at most {MAX_MAGNITUDE:.0e} can be used")
