"""Convex solid primitives (boxes, frusta, ellipsoids, lofts) that procedural shapes are built from.

Every primitive is a convex polyhedron stored as a `ConvexPart`: the triangles of its
surface (for sampling and ray casting) and the half-spaces bounding it (for exact
"is this point strictly inside?" tests). A shape is a union of such parts; the
builder functions here return the *vertices* of a part, which `ConvexPart.from_points`
turns into a closed convex mesh. Curved primitives are polygonal, so the inside test
and the mesh always agree exactly.

Frame: y is up; builders take centres and sizes in any unit (shapes are normalised
afterwards, see `escape_cli.data.shapes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from escape_cli.core.checks import as_points
from escape_cli.errors import DegenerateGeometryError

INSIDE_MARGIN = 1e-6
"""A point is strictly inside a part when it is at least this far inside every face plane."""


@dataclass(frozen=True, eq=False)
class ConvexPart:
    """A closed convex polyhedron.

    Attributes
    ----------
    vertices : (V, 3) float64
        Hull vertices.
    triangles : (F, 3) int64
        Outward-oriented triangles indexing `vertices`.
    planes : (P, 4) float64
        Face planes `(n, d)` with unit outward normal `n`; inside means `n . x + d < 0`.
    lower, upper : (3,) float64
        Axis-aligned bounding box.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    planes: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def from_points(cls, points: np.ndarray) -> "ConvexPart":
        """Build the convex hull of `points`.

        Parameters
        ----------
        points : (V, 3) float64
            Any points; the part is their convex hull.

        Raises
        ------
        DegenerateGeometryError
            When the points span no volume (flat or collinear).
        """
        points = as_points(points, "a convex part's points", min_points=4)
        try:
            hull = ConvexHull(points)
        except Exception as err:  # qhull raises its own QhullError
            raise DegenerateGeometryError(f"convex part spans no volume: {err}") from err
        used = np.unique(hull.simplices)
        remap = np.full(len(points), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        vertices = points[used]
        triangles = remap[hull.simplices]
        normals = hull.equations[:, :3]
        tri = vertices[triangles]  # (F, 3, 3)
        face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3)
        flip = np.einsum("fi,fi->f", face_normals, normals) < 0
        triangles[flip] = triangles[flip][:, ::-1]
        planes = np.unique(np.round(hull.equations, 12), axis=0)  # coplanar facets share a plane
        return cls(vertices, triangles, planes, vertices.min(axis=0), vertices.max(axis=0))

    def contains_strictly(self, points: np.ndarray, margin: float = INSIDE_MARGIN) -> np.ndarray:
        """Which points lie strictly inside the part (not on its surface).

        Parameters
        ----------
        points : (N, 3) float64
        margin : float
            Depth below every face plane a point needs to count as inside.

        Returns
        -------
        inside : (N,) bool
        """
        points = np.asarray(points, dtype=np.float64)
        inside = np.all((points > self.lower + margin) & (points < self.upper - margin), axis=1)
        if inside.any():
            candidates = points[inside]
            depth = candidates @ self.planes[:, :3].T + self.planes[:, 3]  # (n, P)
            inside[inside] = np.all(depth < -margin, axis=1)
        return inside

    def surface_area(self) -> float:
        """Total area of the part's triangles."""
        tri = self.vertices[self.triangles]
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def rotation_matrix(axis: str | np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` radians about `axis` ('x', 'y', 'z' or a 3-vector), right-handed.

    Returns
    -------
    rotation : (3, 3) float64
    """
    if isinstance(axis, str):
        axis = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}[axis]
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def box(center, size, rotation: np.ndarray | None = None) -> np.ndarray:
    """Corners of a box.

    Parameters
    ----------
    center : (3,) float
    size : (3,) float
        Full edge lengths along the box's own x, y, z.
    rotation : (3, 3) float64, optional
        Orientation of the box's axes.

    Returns
    -------
    corners : (8, 3) float64
    """
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners = signs * (0.5 * np.asarray(size, dtype=np.float64))
    if rotation is not None:
        corners = corners @ np.asarray(rotation).T
    return corners + np.asarray(center, dtype=np.float64)


def box_between(lower, upper) -> np.ndarray:
    """Corners of the axis-aligned box spanning `lower` to `upper`, both (3,)."""
    lower = np.asarray(lower, dtype=np.float64)
    upper = np.asarray(upper, dtype=np.float64)
    return box((lower + upper) / 2, upper - lower)


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(axis, u)


def frustum(
    p0, p1, r0: float, r1: float, segments: int = 20, aspect: float = 1.0, angle_offset: float = 0.0
) -> np.ndarray:
    """Vertices of a (possibly tapered, possibly elliptic) cylinder from `p0` to `p1`.

    Parameters
    ----------
    p0, p1 : (3,) float
        Centres of the two end caps.
    r0, r1 : float
        Cap radii; a radius of 0 makes that end a cone apex.
    segments : int
        Polygon sides of the cross-section.
    aspect : float
        Ratio of the second cross-section semi-axis to the first (1 = circular).
    angle_offset : float
        Rotation of the polygon about the axis, radians.

    Returns
    -------
    vertices : (V, 3) float64
    """
    p0 = np.asarray(p0, dtype=np.float64)
    p1 = np.asarray(p1, dtype=np.float64)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    if length <= 0:
        raise DegenerateGeometryError("frustum with zero length")
    u, v = _perpendicular_basis(axis / length)
    angles = np.linspace(0, 2 * np.pi, segments, endpoint=False) + angle_offset
    ring = np.cos(angles)[:, None] * u + aspect * np.sin(angles)[:, None] * v  # (S, 3)
    caps = []
    for centre, radius in ((p0, r0), (p1, r1)):
        caps.append(centre[None] if radius <= 0 else centre + radius * ring)
    return np.concatenate(caps)


def beam(p0, p1, width: float, depth: float | None = None) -> np.ndarray:
    """Vertices of a straight bar with a rectangular `width` x `depth` section from `p0` to `p1`.

    For a vertical bar the section edges are aligned with x and z.

    Returns
    -------
    vertices : (8, 3) float64
    """
    depth = width if depth is None else depth
    return frustum(p0, p1, width / np.sqrt(2), width / np.sqrt(2), segments=4, aspect=depth / width,
                   angle_offset=np.pi / 4)


def ellipsoid(center, radii, rotation: np.ndarray | None = None, rings: int = 10, segments: int = 18) -> np.ndarray:
    """Vertices of a polygonal ellipsoid (latitude-longitude grid plus the poles).

    Parameters
    ----------
    center : (3,) float
    radii : (3,) float
        Semi-axes along the ellipsoid's own x, y, z.
    rotation : (3, 3) float64, optional

    Returns
    -------
    vertices : (V, 3) float64
    """
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    unit = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], axis=-1).reshape(-1, 3)
    unit = np.concatenate([unit, [[0, 1.0, 0], [0, -1.0, 0]]])
    points = unit * np.asarray(radii, dtype=np.float64)
    if rotation is not None:
        points = points @ np.asarray(rotation).T
    return points + np.asarray(center, dtype=np.float64)


def half_ellipsoid(center, radii, rings: int = 6, segments: int = 18, downward: bool = True) -> np.ndarray:
    """Vertices of a half ellipsoid cut by the horizontal plane through `center` (a dome or bowl).

    Parameters
    ----------
    center : (3,) float
        Centre of the flat cut.
    radii : (3,) float
    downward : bool
        The curved side hangs below the cut (a bowl) or rises above it (a dome).

    Returns
    -------
    vertices : (V, 3) float64
    """
    theta = np.linspace(0, np.pi / 2, rings + 1)[:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    sign = -1.0 if downward else 1.0
    unit = np.stack([np.cos(t) * np.cos(p), sign * np.sin(t), np.cos(t) * np.sin(p)], axis=-1).reshape(-1, 3)
    unit = np.concatenate([unit, [[0, sign, 0]]])
    return unit * np.asarray(radii, dtype=np.float64) + np.asarray(center, dtype=np.float64)


def loft(sections: list[np.ndarray]) -> np.ndarray:
    """Vertices of the convex hull of several cross-section polygons (tapered, swept solids).

    Parameters
    ----------
    sections : list of (S_i, 3) float64
        Polygons in 3D; the solid is their convex hull.

    Returns
    -------
    vertices : (sum S_i, 3) float64
    """
    return np.concatenate([np.asarray(s, dtype=np.float64) for s in sections])


def airfoil_section(leading_edge, chord: float, thickness: float, points: int = 10) -> np.ndarray:
    """A lens-shaped wing cross-section in a plane of constant z (chord along -x from the leading edge).

    Parameters
    ----------
    leading_edge : (3,) float
        Front tip of the section.
    chord : float
        Length along x (towards -x, the trailing edge).
    thickness : float
        Maximum thickness along y.

    Returns
    -------
    section : (2 * points, 3) float64
    """
    leading_edge = np.asarray(leading_edge, dtype=np.float64)
    s = np.linspace(0, 1, points)
    half = 0.5 * thickness * np.sqrt(np.clip(s * (1 - s), 0, None)) * 2 * (1 - 0.3 * s)
    x = -chord * s
    upper = np.stack([x, half, np.zeros_like(s)], axis=1)
    lower = np.stack([x, -half, np.zeros_like(s)], axis=1)
    return np.concatenate([upper, lower]) + leading_edge


def polygon_section(outline_yz: np.ndarray, x: float) -> np.ndarray:
    """Place a (S, 2) outline given in (y, z) into the plane of constant `x`; returns (S, 3)."""
    outline_yz = np.asarray(outline_yz, dtype=np.float64)
    return np.column_stack([np.full(len(outline_yz), x), outline_yz[:, 0], outline_yz[:, 1]])


# ----------------------------------------------------------- rounded parts and shells

# 26 unit directions (cube faces, edges and corners): the sphere the rounding sweeps.
_ROUNDING_DIRECTIONS = np.array(
    [d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], dtype=np.float64
) - 1.0
_ROUNDING_DIRECTIONS /= np.linalg.norm(_ROUNDING_DIRECTIONS, axis=1, keepdims=True)


def rounded(vertices, radius: float) -> np.ndarray:
    """Vertices of a convex part with its edges and corners rounded by about `radius`.

    The part is shrunk towards its centre by `radius` along each axis and swept by a
    26-direction sphere of that radius (a Minkowski sum), so its bounding box stays the
    same and its faces keep their planes: a box becomes a box with rounded edges, like
    a cushion, a car body or a cabinet's top.

    Parameters
    ----------
    vertices : (V, 3) float
    radius : float
        At most 0.45 of the part's smallest extent (clamped).

    Returns
    -------
    vertices : (26 V, 3) float64
    """
    points = np.asarray(vertices, dtype=np.float64)
    lower, upper = points.min(axis=0), points.max(axis=0)
    extent = upper - lower
    radius = float(min(radius, 0.45 * extent.min()))
    if radius <= 0:
        return points
    centre = (lower + upper) / 2
    shrunk = centre + (points - centre) * (1.0 - 2.0 * radius / extent)  # (V, 3)
    return (shrunk[:, None, :] + radius * _ROUNDING_DIRECTIONS[None]).reshape(-1, 3)


def grid_shell(surface: np.ndarray, thickness: float, overlap: float = 0.15) -> list[np.ndarray]:
    """A thin curved wall as convex slabs: one per cell of a gridded surface, `thickness` deep.

    Each cell's four corners and the same corners moved `thickness` along minus the
    surface normal make one convex slab; slabs are widened by `overlap` of their size
    on every side so that neighbours overlap, which buries the faces they share (the
    outer-surface sampler drops points strictly inside another part). Hollow shapes,
    an open lamp shade, a boat's hull, a curved chair back, are unions of such slabs.

    Parameters
    ----------
    surface : (U, V, 3) float
        Grid of points on the outer side of the wall (U, V >= 2). The normal is
        d/du x d/dv; the wall grows to the other side.
    thickness : float
    overlap : float

    Returns
    -------
    slabs : list of (8, 3) float64, (U - 1) x (V - 1) of them.
    """
    grid = np.asarray(surface, dtype=np.float64)
    if grid.ndim != 3 or grid.shape[2] != 3 or min(grid.shape[:2]) < 2:
        raise DegenerateGeometryError(f"a shell needs a (U>=2, V>=2, 3) grid, got {grid.shape}")
    du = np.gradient(grid, axis=0)
    dv = np.gradient(grid, axis=1)
    normal = np.cross(du, dv)  # (U, V, 3)
    length = np.linalg.norm(normal, axis=2, keepdims=True)
    if not np.all(length > 0):
        raise DegenerateGeometryError("a shell's grid has a degenerate cell (zero normal)")
    inner = grid - thickness * normal / length
    slabs = []
    for i in range(grid.shape[0] - 1):
        for j in range(grid.shape[1] - 1):
            corners = np.concatenate([grid[i:i + 2, j:j + 2].reshape(4, 3), inner[i:i + 2, j:j + 2].reshape(4, 3)])
            centre = corners.mean(axis=0)
            slabs.append(centre + (corners - centre) * (1.0 + overlap))
    return slabs


def revolved_grid(radii, heights, segments: int = 24, centre=(0.0, 0.0, 0.0), closed: bool = True) -> np.ndarray:
    """A surface of revolution about the vertical axis through `centre`, as a (P, S(+1), 3) grid for `grid_shell`.

    Parameters
    ----------
    radii, heights : (P,) float
        The profile: radius and height (relative to `centre`) of each ring, in order
        along the wall (bottom to top for an outward normal).
    segments : int
        Points per ring.
    closed : bool
        Repeat the first angle at the end, so the shell goes all the way round.

    Returns
    -------
    grid : (P, S + closed, 3) float64
    """
    radii = np.asarray(radii, dtype=np.float64)
    heights = np.asarray(heights, dtype=np.float64)
    angles = np.linspace(0.0, 2 * np.pi, segments + 1 if closed else segments, endpoint=closed)
    ring = np.stack([np.cos(angles), np.zeros_like(angles), np.sin(angles)], axis=1)  # (S, 3): d/du x d/dv points out
    grid = radii[:, None, None] * ring[None] + heights[:, None, None] * np.array([0.0, 1.0, 0.0])
    return grid + np.asarray(centre, dtype=np.float64)
