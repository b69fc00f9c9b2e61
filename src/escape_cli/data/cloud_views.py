"""Depth-camera views of a point cloud that occlude like views of its surface.

A sparse cloud (ModelNet's 1024 points) seen through a plain point z-buffer shows its
far side through the gaps between points: such a "view" covers half the shape, where a
depth render of the mesh covers about a third, and a network trained on it learns that
a view shows most of the object. Here every point of the source cloud becomes a small
disc in its local tangent plane (surface splatting), with a radius set by the local
point spacing, so the discs close the surface; the depth of the nearest disc at every
pixel is the z-buffer, and a point of the complete cloud is seen when it lies on that
front surface. Sparse clouds are first densified in the same tangent planes, so the
complete cloud has PCN's 16384 points without being fuzzier than its source.

Legend: S source points, M complete points, H x W image.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from escape_cli.data.depth_views import DepthCamera, views_from_random_viewpoints
from escape_cli.errors import DegenerateGeometryError

NORMAL_NEIGHBOURS = 10
"""Neighbours of a source point for its tangent plane."""
SPACING_NEIGHBOURS = 6
"""Neighbours whose mean distance is a source point's local spacing."""


@dataclass(frozen=True)
class SplatSettings:
    """How a cloud is densified and splatted.

    Attributes
    ----------
    splat_scale : float
        Disc radius of a source point, in units of its local spacing (the mean distance
        to its 6 nearest neighbours). Chosen by matching view coverage to depth renders
        of meshes (docs/DATASET.md).
    densify_scale : float
        New points are drawn in a disc of this radius (in local spacings) about their
        source point, shrunk where the neighbourhood is not flat.
    depth_tolerance : float
        A point is seen when its own disc, where the ray of its pixel meets it, lies
        within this distance of the front surface (the cloud's bounding-box diagonal is
        1): the two sides of a part thinner than this are both seen.
    """

    splat_scale: float = 1.0
    densify_scale: float = 0.75
    depth_tolerance: float = 0.01


@dataclass(frozen=True)
class TangentFrames:
    """Local geometry of a cloud.

    Attributes
    ----------
    normals : (S, 3) float64, unit, unoriented.
    tangents : (S, 2, 3) float64, unit, orthogonal to the normal and each other.
    spacing : (S,) float64, mean distance to the nearest neighbours.
    flatness : (S,) float64 in [0, 1]: 1 on a plane, 0 where the neighbourhood is not a surface.
    """

    normals: np.ndarray
    tangents: np.ndarray
    spacing: np.ndarray
    flatness: np.ndarray


def tangent_frames(points: np.ndarray) -> TangentFrames:
    """Normals, tangents, spacing and flatness of every point from its nearest neighbours.

    points : (S, 3) float64, S >= 4.
    """
    from escape_cli.core.neighbours import NeighbourIndex

    k = min(NORMAL_NEIGHBOURS, len(points))
    dist, rows = NeighbourIndex(points).query(points, k)  # (S, k): self first
    neighbourhood = points[rows]  # (S, k, 3)
    centred = neighbourhood - neighbourhood.mean(axis=1, keepdims=True)
    cov = np.einsum("ski,skj->sij", centred, centred) / k  # (S, 3, 3)
    eigenvalues, eigenvectors = np.linalg.eigh(cov)  # ascending
    variation = eigenvalues[:, 0] / np.maximum(eigenvalues.sum(axis=1), 1e-300)  # in [0, 1/3]
    spacing = dist[:, 1 : 1 + SPACING_NEIGHBOURS].mean(axis=1)
    return TangentFrames(
        normals=eigenvectors[:, :, 0],
        tangents=np.stack([eigenvectors[:, :, 2], eigenvectors[:, :, 1]], axis=1),
        spacing=spacing,
        flatness=np.clip(1.0 - 6.0 * variation, 0.0, 1.0),
    )


def densify(points: np.ndarray, frames: TangentFrames, n_points: int, rng: np.random.Generator,
            settings: SplatSettings = SplatSettings(), max_rounds: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """The source points plus new ones in their tangent planes, `n_points` in all.

    New points are drawn in a disc about a random source point (radius `densify_scale`
    local spacings, shrunk where the neighbourhood is not flat) and kept only when that
    source point is their nearest: each fills its own Voronoi cell of the surface, so
    the new points spread evenly instead of clumping about the sources.

    Parameters
    ----------
    points : (S, 3) float64, S <= n_points.
    frames : TangentFrames of `points`.
    n_points : int
    rng : numpy.random.Generator
    settings : SplatSettings

    Returns
    -------
    dense : (n_points, 3) float64, the S source points first.
    parent : (n_points,) int64, the source point each row lies about.
    """
    from escape_cli.core.neighbours import NeighbourIndex

    s = len(points)
    index = NeighbourIndex(points)
    kept_points, kept_parents, need = [], [], n_points - s
    for _ in range(max_rounds):
        if need <= 0:
            break
        count = 2 * need + 64
        parent = rng.integers(0, s, count)
        radius = settings.densify_scale * frames.spacing[parent] * frames.flatness[parent] * np.sqrt(rng.random(count))
        angle = rng.uniform(0.0, 2.0 * np.pi, count)
        t = frames.tangents[parent]  # (C, 2, 3)
        candidates = points[parent] + radius[:, None] * (np.cos(angle)[:, None] * t[:, 0] + np.sin(angle)[:, None] * t[:, 1])
        _, nearest = index.query(candidates, 1)
        own = np.flatnonzero(nearest[:, 0] == parent)[:need]
        kept_points.append(candidates[own])
        kept_parents.append(parent[own])
        need -= len(own)
    if need > 0:
        raise DegenerateGeometryError(f"cannot densify {s} points to {n_points}")
    return np.concatenate([points, *kept_points]), np.concatenate([np.arange(s), *kept_parents]).astype(np.int64)


def _look_at(eye: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Rows: camera right, up and forward (towards the origin); (3, 3) float64."""
    forward = -eye / np.linalg.norm(eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(right, forward), forward])


class SplatScanner:
    """Depth views of a cloud whose source points are discs in their tangent planes.

    Parameters
    ----------
    source : (S, 3) float64, the discs' centres.
    frames : TangentFrames of `source`.
    complete : (M, 3) float64, the points a view may show.
    parent : (M,) int64, the source point whose disc each complete point lies on.
    camera : DepthCamera
    settings : SplatSettings
    """

    def __init__(self, source, frames: TangentFrames, complete, parent, camera: DepthCamera = DepthCamera(),
                 settings: SplatSettings = SplatSettings()):
        self.source, self.frames = source, frames
        self.complete, self.parent = complete, parent
        self.camera, self.settings = camera, settings
        self.radius = settings.splat_scale * frames.spacing  # (S,)
        self.focal = 0.5 * camera.width / np.tan(np.radians(camera.fov_deg) / 2)

    def _project(self, points: np.ndarray, basis: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """(P, 3) world -> (P, 3) camera (x right, y up, z depth)."""
        return (points - eye) @ basis.T

    def _disc_depths(self, centres, normals, radius, pixels):
        """Depth of each disc where the ray of its candidate pixel meets it (inf where it misses).

        centres, normals : (P, 3) in camera coordinates; radius : (P,); pixels : (P, 2) int.
        """
        cam = self.camera
        ray = np.column_stack([
            (pixels[:, 0] + 0.5 - cam.width / 2) / self.focal,
            -(pixels[:, 1] + 0.5 - cam.height / 2) / self.focal,
            np.ones(len(pixels)),
        ])  # (P, 3), z = 1
        along = np.einsum("pi,pi->p", normals, ray)
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.einsum("pi,pi->p", normals, centres) / along  # the plane's depth on the ray
        hit = ray * depth[:, None]
        inside = (np.abs(along) > 1e-3) & (depth > 0) & (np.einsum("pi,pi->p", hit - centres, hit - centres) <= radius * radius)
        return np.where(inside, depth, np.inf)

    def scan(self, eye: np.ndarray, up: np.ndarray) -> np.ndarray:
        """The complete cloud's points seen from `eye` looking at the origin -> (V, 3) float64."""
        cam = self.camera
        basis = _look_at(eye, up)
        centres = self._project(self.source, basis, eye)  # (S, 3)
        normals = self.frames.normals @ basis.T  # (S, 3)
        z = centres[:, 2]
        front = z > 1e-6
        u = cam.width / 2 + self.focal * centres[:, 0] / np.where(front, z, 1)
        v = cam.height / 2 - self.focal * centres[:, 1] / np.where(front, z, 1)
        reach = np.where(front, self.radius * self.focal / np.where(front, z, 1), 0)  # disc radius in pixels
        zbuf = self._zbuffer(centres, normals, u, v, reach, front)
        return self.complete[self._seen(basis, eye, normals, zbuf)]

    def _zbuffer(self, centres, normals, u, v, reach, front) -> np.ndarray:
        """(H * W,) depth of the nearest disc at every pixel (inf where none): `_zbuffer_naive`'s, exactly.

        Each disc is tried on the pixels of its own reach (`_zbuffer_naive` tries every disc on
        the pixels of the largest, so one isolated point with a wide disc made every view of a
        16384-point cloud 50x slower and 10x bigger): the discs are grouped by that reach and
        each group offset as far as a pixel could pass the distance test, plus one pixel;
        what a disc adds to the buffer is the same, and a minimum does not depend on order.
        """
        max_reach = int(np.ceil(min(reach.max(initial=0.0), 16.0)))
        # |offset| - 0.5 <= the pixel centre's distance <= reach + 0.71 (the naive test): |offset| <= reach + 1.21
        own = np.minimum(np.ceil(reach + 1.21).astype(np.int64) + 1, max_reach)
        zbuf = np.full(self.camera.width * self.camera.height, np.inf)
        for r in np.unique(own[front]):
            rows = np.flatnonzero(front & (own == r))
            self._splat(zbuf, centres[rows], normals[rows], u[rows], v[rows], reach[rows], self.radius[rows], int(r))
        return zbuf

    def _zbuffer_naive(self, centres, normals, u, v, reach, front) -> np.ndarray:
        """The reference of `_zbuffer`: every disc tried on the pixels of the largest reach (at most 16)."""
        max_reach = int(np.ceil(min(reach.max(initial=0.0), 16.0)))
        zbuf = np.full(self.camera.width * self.camera.height, np.inf)
        rows = np.flatnonzero(front)
        self._splat(zbuf, centres[rows], normals[rows], u[rows], v[rows], reach[rows], self.radius[rows], max_reach)
        return zbuf

    def _splat(self, zbuf, centres, normals, u, v, reach, radius, max_reach: int) -> None:
        """Lower `zbuf` to the depth of every disc at each pixel within `max_reach` of its centre that it covers."""
        cam = self.camera
        steps = np.arange(-max_reach, max_reach + 1)
        dx, dy = (a.reshape(1, -1) for a in np.meshgrid(steps, steps))  # (1, O) pixel offsets
        cx, cy = np.floor(u).astype(np.int64)[:, None] + dx, np.floor(v).astype(np.int64)[:, None] + dy  # (S, O)
        near = np.hypot(cx + 0.5 - u[:, None], cy + 0.5 - v[:, None]) <= reach[:, None] + 0.71
        near &= (cx >= 0) & (cx < cam.width) & (cy >= 0) & (cy < cam.height)
        rows, cols = np.nonzero(near)
        if len(rows):
            pix = np.column_stack([cx[rows, cols], cy[rows, cols]])
            depth = self._disc_depths(centres[rows], normals[rows], radius[rows], pix)
            np.minimum.at(zbuf, pix[:, 1] * cam.width + pix[:, 0], depth)

    def _seen(self, basis, eye, normals, zbuf) -> np.ndarray:
        """Rows of the complete points a depth camera returns: on the front surface, the nearest one per pixel.

        Returns (V,) int64, ascending.
        """
        cam = self.camera
        p = self._project(self.complete, basis, eye)  # (M, 3)
        z = p[:, 2]
        front = z > 1e-6
        safe = np.where(front, z, 1)
        px = np.floor(cam.width / 2 + self.focal * p[:, 0] / safe).astype(np.int64)
        py = np.floor(cam.height / 2 - self.focal * p[:, 1] / safe).astype(np.int64)
        inside = front & (px >= 0) & (px < cam.width) & (py >= 0) & (py < cam.height)
        surface = np.full(len(p), np.inf)
        surface[inside] = zbuf[py[inside] * cam.width + px[inside]]
        # the depth of the point's own disc plane at its pixel's centre, as the z-buffer measured it
        centres = self._project(self.source, basis, eye)[self.parent]  # (M, 3)
        n = normals[self.parent]  # (M, 3)
        ray = np.column_stack([(px + 0.5 - cam.width / 2) / self.focal, -(py + 0.5 - cam.height / 2) / self.focal, np.ones(len(p))])
        along = np.einsum("mi,mi->m", n, ray)
        with np.errstate(divide="ignore", invalid="ignore"):
            own = np.einsum("mi,mi->m", n, centres) / along
        own = np.where(np.abs(along) > 0.2 * np.linalg.norm(ray, axis=1), own, z)  # within ~78 degrees of the ray
        rows = np.flatnonzero(inside & (own <= surface + self.settings.depth_tolerance))
        pixel = py[rows] * cam.width + px[rows]
        order = np.lexsort((z[rows], pixel))  # by pixel, nearest first
        first = np.ones(len(order), dtype=bool)
        first[1:] = pixel[order][1:] != pixel[order][:-1]
        return np.sort(rows[order[first]])  # one point per pixel, like a depth image

    def random_views(self, n_views: int, rng: np.random.Generator) -> list[np.ndarray]:
        """`n_views` views from random viewpoints (drawn like `DepthScanner.random_views`).

        Returns
        -------
        views : list of (V_i, 3) float64, each with at least `camera.min_points` points.

        Raises
        ------
        DegenerateGeometryError
            When a view keeps showing fewer than `camera.min_points` points.
        """
        return views_from_random_viewpoints(self.scan, self.camera, n_views, rng)


def view_coverage(complete: np.ndarray, view: np.ndarray, fraction: float = 0.02) -> float:
    """Share of the complete cloud within `fraction` of its bounding-box diagonal of a view point.

    complete : (M, 3) float, view : (V, 3) float -> float in [0, 1]
    """
    from escape_cli.core.neighbours import NeighbourIndex

    diagonal = float(np.linalg.norm(np.ptp(complete, axis=0)))
    limit = fraction * diagonal
    dist, _ = NeighbourIndex(view).query(complete, 1, limit=limit)
    return float(np.mean(dist[:, 0] <= limit))
