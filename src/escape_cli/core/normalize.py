"""Normalisations with exact inverses: the scan's own frame, centroid + radius, and KITTI boxes.

The network only knows the scale it was trained at (distances are rotation- and
translation-invariant, not scale-invariant). `PartialFrame` is the frame the current
models are trained and run in: it is computed from the partial alone, so a scan in
millimetres, metres or PCN units reaches the network identically. `fit_normalization`
is the older heuristic (centroid + RMS radius of all points, scaled to the median
training partial) kept for models trained in absolute PCN units;
`box_normalization` is the PCN/PoinTr convention for KITTI cars, which uses the
detector's box instead.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from escape_cli.core.checks import as_points, as_vector
from escape_cli.core.params import as_count, as_number
from escape_cli.core.sampling import power_of_two_unit
from escape_cli.errors import DegenerateGeometryError, EscapeError

__all__ = [
    "NetworkInput",
    "PartialFrame",
    "network_input",
    "Normalization",
    "cloud_radius",
    "cloud_radius_naive",
    "fit_normalization",
    "BoxNormalization",
    "box_normalization",
]


def _as_vector3(value, name: str) -> np.ndarray:
    vec = as_vector(value, name, 3).copy()
    vec.setflags(write=False)
    return vec


def _as_scale(value, name: str = "scale") -> float:
    return as_number(value, name, above=0.0)


# ------------------------------------------------------------ centroid + radius


@dataclass(frozen=True, eq=False)
class Normalization:
    """A similarity without rotation: ``apply(p) = (p - center) / scale``.

    Attributes
    ----------
    center : (3,) float64
        Subtracted first (read-only array).
    scale : float
        Divided by next; > 0.
    """

    center: np.ndarray
    scale: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _as_vector3(self.center, "center"))
        object.__setattr__(self, "scale", _as_scale(self.scale))

    @classmethod
    def identity(cls) -> "Normalization":
        """The normalisation that changes nothing (centre 0, scale 1): 'turned off'."""
        return cls(np.zeros(3), 1.0)

    def apply(self, points) -> np.ndarray:
        """(N, 3) points in the input frame -> (N, 3) normalised points."""
        return (as_points(points, "points", min_points=0) - self.center) / self.scale

    def invert(self, points) -> np.ndarray:
        """(N, 3) normalised points -> (N, 3) points in the input frame."""
        return as_points(points, "points", min_points=0) * self.scale + self.center

    def to_dict(self) -> dict:
        """JSON-ready ``{"center": [x, y, z], "scale": s}``."""
        return {"center": [float(v) for v in self.center], "scale": float(self.scale)}

    @classmethod
    def from_dict(cls, data: dict) -> "Normalization":
        """Inverse of `to_dict`; raises EscapeError on missing keys or bad values."""
        try:
            return cls(data["center"], data["scale"])
        except (KeyError, TypeError) as exc:
            raise EscapeError(f"not a normalisation record (need 'center' and 'scale'): {exc}") from exc


def cloud_radius(points, quantile: float | None = None) -> float:
    """A rotation-invariant radius of a cloud about its centroid.

    With ``quantile=None`` (the default) the RMS distance from the centroid,

        r = sqrt( mean_i ||p_i - mean(p)||^2 ),

    which is smooth in the points and unchanged by rotation, translation and point
    order. With ``quantile=q`` the q-quantile of ||p_i - mean(p)|| instead (less
    sensitive to a few stray points, but a step function of them).

    Parameters
    ----------
    points : (N, 3) float
    quantile : float in (0, 1] or None

    Returns
    -------
    float
        Raises DegenerateGeometryError when the radius is zero (all points equal).
    """
    pts = as_points(points, "points", min_points=1)
    centred = pts - pts.mean(axis=0)  # (N, 3)
    unit = power_of_two_unit(centred)  # exact rescaling: no underflow or overflow of the squares
    centred = centred * unit
    dist = np.sqrt((centred * centred).sum(axis=1))  # (N,)
    if quantile is None:
        radius = float(np.sqrt(np.mean(dist * dist)))
    else:
        q = float(quantile)
        if not 0.0 < q <= 1.0:
            raise EscapeError(f"radius quantile must be in (0, 1], got {quantile}")
        radius = float(np.quantile(dist, q))
    radius /= unit
    extent = float(np.abs(pts).max())
    if not radius > 1e-12 * extent:
        raise DegenerateGeometryError(
            f"cloud of {len(pts)} points has zero radius (all points equal): cannot normalise"
        )
    return radius


def cloud_radius_naive(points) -> float:
    """Reference for `cloud_radius` (RMS): a plain loop over the points."""
    pts = [tuple(map(float, p)) for p in as_points(points, "points", min_points=1)]
    n = len(pts)
    c = [sum(p[k] for p in pts) / n for k in range(3)]
    return float(np.sqrt(sum(sum((p[k] - c[k]) ** 2 for k in range(3)) for p in pts) / n))


def fit_normalization(points, target_radius: float, quantile: float | None = None) -> Normalization:
    """The normalisation that centres a cloud and gives it `target_radius`.

    center = mean of the points; scale = cloud_radius(points) / target_radius, so
    ``cloud_radius(norm.apply(points)) == target_radius``. Both are rotation-invariant
    in the sense that fitting on ``points @ R.T + t`` gives the centre ``R c + t`` and
    the same scale.

    Parameters
    ----------
    points : (N, 3) float
        The partial scan, in its own units.
    target_radius : float
        The radius statistic of the network's training partials (measure it with
        `cloud_radius` on them, with the same `quantile`).
    quantile : float or None
        Passed to `cloud_radius`.

    Returns
    -------
    Normalization
    """
    target = _as_scale(target_radius, "target_radius")
    pts = as_points(points, "points", min_points=0)
    radius = cloud_radius(pts, quantile=quantile)
    return Normalization(pts.mean(axis=0), radius / target)


# ------------------------------------------------------------ the scan's own frame


@dataclass(frozen=True)
class PartialFrame:
    """The frame a partial scan is completed in, computed from the partial alone.

    The scan's first `rows` farthest-point rows (the network input's coarse cover of the
    visible surface, so dense near surfaces do not weigh more) are centred on their
    centroid and scaled to an RMS radius of `radius`. Among the statistics measured on
    the training partials this one predicted the complete shape's size best (std of
    log(complete radius / statistic) 0.099, against 0.115 for the RMS radius of all
    points and 0.178 for absolute PCN units) while moving by only 2.6% when 1% of the
    points are outliers (64 rows: 0.093 but 8%).

    Attributes
    ----------
    rows : int
        Farthest-point rows the statistic is taken on.
    radius : float
        Their RMS radius in the frame (PCN-like units: about the training partials').
    """

    rows: int = 256
    radius: float = 0.28

    def __post_init__(self) -> None:
        as_count(self.rows, "frame rows", minimum=4)
        _as_scale(self.radius, "frame radius")

    def fit(self, ordered) -> "Normalization":
        """The normalisation of a cloud given in farthest-point order.

        Parameters
        ----------
        ordered : (N, 3) float
            Distinct points, farthest-point ordered (the leading rows of `prepare_input`).
        """
        head = as_points(ordered, "the ordered cloud", min_points=1)[: self.rows]  # (R, 3)
        centre = head.mean(axis=0)
        return Normalization(centre, cloud_radius(head) / self.radius)

    def to_dict(self) -> dict:
        return {"kind": "partial", "rows": int(self.rows), "radius": float(self.radius)}


@dataclass(frozen=True, eq=False)
class NetworkInput:
    """A scan made ready for the network (see `network_input`).

    Attributes
    ----------
    rows : (S, 3) float64
        The farthest-point-ordered input in the network's frame (short scans repeated).
    unique : int
        Leading rows of `rows` that are distinct points.
    normalization : Normalization
        Maps the scan into the network's frame; `invert` maps results back.
    """

    rows: np.ndarray
    unique: int
    normalization: "Normalization"

    @property
    def observed(self) -> np.ndarray:
        """(unique, 3) the distinct observed points, in the network's frame."""
        return self.rows[: self.unique]


def network_input(points, size: int, frame: PartialFrame | None = PartialFrame()) -> NetworkInput:
    """The farthest-point-ordered network input of a scan, in the scan's own frame.

    Used by training (`escape_cli.nn.samples`) and by `complete`, so both feed the
    network the same rows. The scan is first centred on its mean in float64 (scans in
    UTM metres keep their precision), then ordered by farthest point sampling, then
    mapped by `frame.fit` of those rows; ``frame=None`` keeps the units as they are
    (models trained in absolute PCN units), centred or not alike for the network.

    The result is similarity-equivariant: for ``s R x + t`` the rows are ``s R rows + t``
    before normalisation, and identical after it (up to rounding).

    Parameters
    ----------
    points : (N, 3) float
        The scan, N >= 1, any units and position.
    size : int
        Rows of the network input.
    frame : PartialFrame or None

    Returns
    -------
    NetworkInput
    """
    from escape_cli.core.sampling import prepare_input

    pts = as_points(points, "the scan", min_points=1)
    offset = pts.mean(axis=0)  # (3,)
    prepared, unique = prepare_input(pts - offset, size)  # (S, 3)
    if frame is None:
        return NetworkInput(prepared + offset, unique, Normalization.identity())
    local = frame.fit(prepared[:unique])
    norm = Normalization(local.center + offset, local.scale)
    return NetworkInput((prepared - local.center) / local.scale, unique, norm)


# ------------------------------------------------------------------ KITTI boxes


@dataclass(frozen=True, eq=False)
class BoxNormalization:
    """A rigid motion plus a scale into a box's frame: ``apply(p) = rotation @ (p - center) / scale``.

    Unpacks as a tuple: ``rotation, center, scale = box_normalization(corners)``.

    Attributes
    ----------
    rotation : (3, 3) float64
        Orthonormal; its rows are the box axes expressed in the input frame. With the
        PCN axes (the default of `box_normalization`) the determinant is -1 (see there).
    center : (3,) float64
        The box centre in the input frame.
    scale : float
        The box length.
    """

    rotation: np.ndarray
    center: np.ndarray
    scale: float

    def __post_init__(self) -> None:
        rot = np.asarray(self.rotation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise EscapeError(f"rotation must be a finite (3, 3) matrix, got shape {rot.shape}")
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9):
            raise EscapeError("rotation must be orthonormal")
        rot = rot.copy()
        rot.setflags(write=False)
        object.__setattr__(self, "rotation", rot)
        object.__setattr__(self, "center", _as_vector3(self.center, "center"))
        object.__setattr__(self, "scale", _as_scale(self.scale))

    def __iter__(self):
        return iter((self.rotation, self.center, self.scale))

    def apply(self, points) -> np.ndarray:
        """(N, 3) points in the LiDAR frame -> (N, 3) points in the box frame."""
        return ((as_points(points, "points", min_points=0) - self.center) @ self.rotation.T) / self.scale  # (N, 3)

    def invert(self, points) -> np.ndarray:
        """(N, 3) points in the box frame -> (N, 3) points in the LiDAR frame."""
        return (as_points(points, "points", min_points=0) * self.scale) @ self.rotation + self.center  # (N, 3)

    def to_dict(self) -> dict:
        """JSON-ready ``{"rotation": 3x3 list, "center": [x, y, z], "scale": s}``."""
        return {
            "rotation": [[float(v) for v in row] for row in self.rotation],
            "center": [float(v) for v in self.center],
            "scale": float(self.scale),
        }

    @classmethod
    def from_dict(cls, data: dict) -> "BoxNormalization":
        """Inverse of `to_dict`."""
        try:
            return cls(data["rotation"], data["center"], data["scale"])
        except (KeyError, TypeError, ValueError) as exc:
            raise EscapeError(
                f"not a box normalisation record (need 'rotation', 'center', 'scale'): {exc}"
            ) from exc


def box_normalization(corners, pcn_axes: bool = True, tol: float = 0.02) -> BoxNormalization:
    """The KITTI car normalisation of PCN and PoinTr, from a box's 8 corners.

    Corners are in PCN order (wentaoyuan/pcn ``process_kitti_raw.py``): 0-3 the bottom
    face going round, 4-7 the top face above them, ``bbox[3] - bbox[0]`` along the
    length and ``bbox[4] - bbox[0]`` up. Then

    - center = mean of the 8 corners (the box centre);
    - u = unit(bbox[3] - bbox[0]) (length axis), w = bbox[4] - bbox[0] made
      orthogonal to u and unit (up axis);
    - scale = ||bbox[3] - bbox[0]|| (the box length), so the car spans [-0.5, 0.5]
      along its length;
    - ``pcn_axes=True``: rotation rows (u, w, w x u): x = length, y = up, z = lateral,
      which is PCN's ``np.dot(p - center, Rz(yaw)) / scale`` followed by its y/z swap
      ``[[1, 0, 0], [0, 0, 1], [0, 1, 0]]`` -- the ShapeNet frame (y up) the PCN car
      models live in. That swap is a reflection, so det(rotation) = -1.
      ``pcn_axes=False``: rows (u, w x u, w): x = length, y = lateral, z = up, a proper
      rotation (det +1).

    Unlike PCN, which takes the yaw from the horizontal part of the length edge and
    assumes the LiDAR z axis is up, the axes come from the corners in 3D, so the frame
    is equivariant under any rigid motion of scene and box together. On KITTI boxes
    (tilted by ~0.01 rad in the LiDAR frame) the two differ by that tilt.

    Parameters
    ----------
    corners : (8, 3) float
    pcn_axes : bool
    tol : float
        Relative tolerance (of the box length) for checking that the corners form a box.

    Returns
    -------
    BoxNormalization
        Also unpacks as ``rotation, center, scale``.
    """
    box = np.asarray(corners, dtype=np.float64)
    if box.shape != (8, 3):
        raise EscapeError(f"box corners must have shape (8, 3), got {box.shape}")
    if not np.all(np.isfinite(box)):
        raise EscapeError("box corners contain NaN or infinite values")
    length_edge = box[3] - box[0]  # (3,)
    width_edge = box[1] - box[0]  # (3,)
    up_edge = box[4] - box[0]  # (3,)
    length = float(np.linalg.norm(length_edge))
    if length == 0.0:
        raise DegenerateGeometryError("box has zero length (corners 0 and 3 coincide)")
    # Parallelepiped in PCN order: bottom 0,1,2,3 round the face, top = bottom + up.
    expected = np.stack([
        box[0], box[0] + width_edge, box[0] + width_edge + length_edge, box[0] + length_edge,
    ])  # (4, 3)
    expected = np.concatenate([expected, expected + up_edge])  # (8, 3)
    misfit = float(np.abs(box - expected).max())
    u = length_edge / length
    up_perp = up_edge - (up_edge @ u) * u
    height = float(np.linalg.norm(up_perp))
    width = float(np.linalg.norm(width_edge))
    if height <= tol * length or width <= tol * length:
        raise DegenerateGeometryError(
            "box is flat: its up or width edge is (nearly) zero or along its length"
        )
    w = up_perp / height
    cosines = [abs(float(u @ width_edge)) / width, abs(float(w @ width_edge)) / width,
               abs(float(u @ up_edge)) / np.linalg.norm(up_edge)]
    if misfit > tol * length or max(cosines) > tol:
        raise DegenerateGeometryError(
            "corners are not a box in PCN order (bbox[3]-bbox[0] = length, bbox[4]-bbox[0] = up)"
        )
    lateral = np.cross(w, u)  # (3,) unit: w x u
    rotation = np.stack((u, w, lateral) if pcn_axes else (u, lateral, w))  # (3, 3) rows = axes
    return BoxNormalization(rotation, box.mean(axis=0), length)


AXES = "xyz"


def car_in_box_frame(points, up: str) -> list[np.ndarray]:
    """A complete reference car in the frame `box_normalization` gives a KITTI car: both ways round.

    The car is centred on its axis-aligned bounding box and scaled so that its length
    (the longer of its two horizontal extents; `up` names the vertical axis, ``"z"`` for
    ModelNet, ``"y"`` for ShapeNet) is 1; then x = length, y = up, z = lateral (PCN's
    axes). Which end is the front is not known, so the car comes back twice: as it is and
    turned by 180 degrees about y. A car with no extent along its length is refused.

    Parameters
    ----------
    points : (N, 3) float
    up : one of "x", "y", "z"

    Returns
    -------
    [(N, 3), (N, 3)] float64
    """
    if up not in AXES:
        raise ValueError(f"up must be one of x, y, z, got {up!r}")
    pts = as_points(points, "reference car", min_points=1)  # float64
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    vertical = AXES.index(up)
    length, lateral = sorted((a for a in range(3) if a != vertical), key=lambda a: hi[a] - lo[a], reverse=True)
    extent = hi[length] - lo[length]
    if not np.isfinite(extent) or extent <= 0:
        raise DegenerateGeometryError("a reference car has no length (all its points in one plane across it)")
    boxed = ((pts - (lo + hi) / 2) / extent)[:, [length, vertical, lateral]]
    return [boxed, boxed * np.array([-1.0, 1.0, -1.0])]
